/* The lane ring's layout, shared by the module and the C tests (see _ring.c). */
#ifndef BUFFER_PUBSUB_RING_H
#define BUFFER_PUBSUB_RING_H

#include <fcntl.h>
#include <stddef.h>
#include <stdint.h>
#include <string.h>

#define RING_MAGIC "WBLANE\0\1"
#define RING_VERSION 1u
#define RING_HEADER_BYTES 4096u
#define RING_SLOT_HEAD 16u
/* One slot holds a frame of at most MAX_PAYLOAD (8192) bytes, rounded up to a cache line. */
#define RING_DEFAULT_SLOT (8192u + 64u)
#define RING_MAX_DEPTH 1024u
#define RING_MAX_SLOT (1u << 16)
#define RING_SEALS (F_SEAL_SHRINK | F_SEAL_GROW | F_SEAL_SEAL)

typedef struct {
    char magic[8];
    uint32_t version;
    uint32_t depth;
    uint32_t slot_bytes;
    uint32_t writer_pid;
    unsigned char pad0[40];
    /* line 1: the writer's */
    uint64_t tail;           /* frames published */
    uint32_t writer_closed;
    unsigned char pad1[52];
    /* line 2: the reader's (hints to the writer) */
    uint64_t head;           /* frames taken */
    uint32_t waiting;        /* the reader sleeps: ring the doorbell */
    uint32_t reader_closed;
} ring_header;

typedef struct {
    uint64_t stamp;          /* 2n+1 while frame n is written, 2n+2 once complete */
    uint32_t length;
    uint32_t reserved;
    unsigned char data[];
} ring_slot;

_Static_assert(offsetof(ring_header, tail) == 64, "the writer's line");
_Static_assert(offsetof(ring_header, head) == 128, "the reader's line");
_Static_assert(sizeof(ring_header) <= RING_HEADER_BYTES, "header page");
_Static_assert(offsetof(ring_slot, data) == RING_SLOT_HEAD, "slot head");

static inline int ring_geometry_ok(uint32_t depth, uint32_t slot_bytes) {
    return depth >= 1 && depth <= RING_MAX_DEPTH && slot_bytes > RING_SLOT_HEAD
           && slot_bytes <= RING_MAX_SLOT && slot_bytes % 64 == 0;
}

static inline size_t ring_file_size(uint32_t depth, uint32_t slot_bytes) {
    return RING_HEADER_BYTES + (size_t)depth * slot_bytes;
}

static inline ring_slot *ring_slot_at(unsigned char *map, uint32_t depth, uint32_t slot_bytes,
                                      uint64_t n) {
    return (ring_slot *)(map + RING_HEADER_BYTES + (size_t)(n % depth) * slot_bytes);
}

static inline void ring_header_init(ring_header *h, uint32_t depth, uint32_t slot_bytes,
                                    uint32_t pid) {
    memcpy(h->magic, RING_MAGIC, 8);
    h->version = RING_VERSION;
    h->depth = depth;
    h->slot_bytes = slot_bytes;
    h->writer_pid = pid;
}

static inline int ring_header_matches(const ring_header *h, uint32_t depth, uint32_t slot_bytes) {
    return memcmp(h->magic, RING_MAGIC, 8) == 0 && h->version == RING_VERSION
           && h->depth == depth && h->slot_bytes == slot_bytes;
}

#endif
