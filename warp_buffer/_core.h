/* The descriptor's fixed layout (warp_buffer.descriptor.LAYOUT), shared by the module and the
 * C tests: 27 little-endian fields, natural alignment, 192 bytes. */
#ifndef WARP_BUFFER_CORE_H
#define WARP_BUFFER_CORE_H

#include <stdint.h>
#include <string.h>

#define DESC_FIELDS 27
#define DESC_BYTES 192
#define DESC_HANDLE_WORDS 8

/* bytes per field, in FIELDS order: version, kind, peer_slot, owner_pid, session, offset,
 * capacity, size, generation, sequence, device_uuid, mem_handle_0..7, event_handle_0..7 */
static const int DESC_FIELD_WIDTHS[DESC_FIELDS] = {
    1, 1, 2, 4, 8, 8, 8, 8, 8, 8, 8,
    8, 8, 8, 8, 8, 8, 8, 8,
    8, 8, 8, 8, 8, 8, 8, 8,
};

static const char *const DESC_FIELD_NAMES[DESC_FIELDS] = {
    "version", "kind", "peer_slot", "owner_pid", "session", "offset", "capacity", "size",
    "generation", "sequence", "device_uuid",
    "mem_handle_0", "mem_handle_1", "mem_handle_2", "mem_handle_3",
    "mem_handle_4", "mem_handle_5", "mem_handle_6", "mem_handle_7",
    "event_handle_0", "event_handle_1", "event_handle_2", "event_handle_3",
    "event_handle_4", "event_handle_5", "event_handle_6", "event_handle_7",
};

static inline void desc_put(unsigned char *out, uint64_t v, int width) {
    for (int b = 0; b < width; b++)
        out[b] = (unsigned char)(v >> (8 * b));
}

static inline uint64_t desc_get(const unsigned char *in, int width) {
    uint64_t v = 0;
    for (int b = 0; b < width; b++)
        v |= (uint64_t)in[b] << (8 * b);
    return v;
}

static inline void desc_pack(const uint64_t *v, unsigned char *out) {
    int at = 0;
    for (int i = 0; i < DESC_FIELDS; i++) {
        desc_put(out + at, v[i], DESC_FIELD_WIDTHS[i]);
        at += DESC_FIELD_WIDTHS[i];
    }
}

static inline void desc_unpack(const unsigned char *in, uint64_t *v) {
    int at = 0;
    for (int i = 0; i < DESC_FIELDS; i++) {
        v[i] = desc_get(in + at, DESC_FIELD_WIDTHS[i]);
        at += DESC_FIELD_WIDTHS[i];
    }
}


/* ----------------------------------------------------------------------------- the arena file
 * (warp_buffer.arena): header page, one 64-byte acknowledgement slot per peer subscription,
 * one generation word per 4 KiB of data, then the blocks. */
#define ARENA_MIN_BLOCK 4096ULL
#define ARENA_LOCK_SPAN 4096ULL
#define ARENA_MAX_PEERS 1024
#define ARENA_SLOT_STRIDE 64
#define ARENA_NO_PEER 0xFFFF
#define ARENA_ACKS_OFFSET 4096ULL
#define ARENA_GENS_OFFSET (ARENA_ACKS_OFFSET + ARENA_MAX_PEERS * ARENA_SLOT_STRIDE)
#define ARENA_GENERATION_ORDER_BITS 6
#define DESC_VERSION 2
#define DESC_KIND_HOST 0
#define DESC_KIND_CUDA_IPC 1
#define DESC_KIND_CUDA_STAGING 2
#define DESC_KIND_CUDA_VMM 3
#define PID_MAX (1u << 22)

/* field indexes of the descriptor */
enum { F_VERSION, F_KIND, F_SLOT, F_PID, F_SESSION, F_OFFSET, F_CAPACITY, F_SIZE,
       F_GENERATION, F_SEQUENCE, F_DEVICE };

/* ----------------------------------------------------------------------------- shared */
#include <Python.h>
#include <sys/types.h>

#define DESC_FIELD_COUNT_USED 11  /* the import reads the fields up to device_uuid */

extern PyObject *DescriptorError, *ExportBoundsError, *StaleBufferError, *ExportError,
    *RecycledBufferError;
extern PyTypeObject SessionType, HoldType;

/* Raise cls (fallback until set) with a message formatted by printf: numbers only. */
PyObject *raise_as(PyObject *cls, PyObject *fallback, const char *fmt, ...);
PyObject *descriptor_error(const char *fmt, ...);
int field_value(PyObject *item, int i, uint64_t *out);
int lock_range(int fd, short kind, uint64_t offset, uint64_t length);
PyObject *lease_configure(PyObject *module, PyObject *args);
/* This process's pid, kept across forks (pthread_atfork): no system call per check. */
extern pid_t this_pid;
PyObject *check_names(PyObject *module, PyObject *values);
PyObject *set_descriptor_type(PyObject *module, PyObject *args);
PyObject *make_descriptor_py(PyObject *module, PyObject *values);
PyObject *describe(PyObject *module, PyObject *args);
PyObject *sessions_after_fork(PyObject *module, PyObject *unused);
int lease_module_init(PyObject *module);

#endif
