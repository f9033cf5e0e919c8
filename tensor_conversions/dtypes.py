"""DLPack data types: ``(code, bits, lanes)`` <-> canonical names <-> NumPy dtypes.

The codes are DLPack's ``DLDataTypeCode``. Frameworks map their own dtypes through the canonical
names (``"float32"``, ``"bfloat16"``, ...), which NumPy, PyTorch and Warp all spell the same way.
"""

from __future__ import annotations

import enum
from dataclasses import dataclass

import numpy as np

from .errors import UnsupportedDTypeError

__all__ = [
    "DLDataTypeCode",
    "DType",
    "SUPPORTED_DTYPES",
    "dtype_from_metadata",
    "dtype_from_name",
    "dtype_from_numpy",
]


class DLDataTypeCode(enum.IntEnum):
    """DLPack ``DLDataTypeCode`` values (dlpack.h v1.1)."""

    INT = 0
    UINT = 1
    FLOAT = 2
    OPAQUE_HANDLE = 3
    BFLOAT = 4
    COMPLEX = 5
    BOOL = 6
    FLOAT8_E3M4 = 7
    FLOAT8_E4M3 = 8
    FLOAT8_E4M3B11FNUZ = 9
    FLOAT8_E4M3FN = 10
    FLOAT8_E4M3FNUZ = 11
    FLOAT8_E5M2 = 12
    FLOAT8_E5M2FNUZ = 13
    FLOAT8_E8M0FNU = 14
    FLOAT6_E2M3FN = 15
    FLOAT6_E3M2FN = 16
    FLOAT4_E2M1FN = 17


_PREFIX = {
    DLDataTypeCode.INT: "int",
    DLDataTypeCode.UINT: "uint",
    DLDataTypeCode.FLOAT: "float",
    DLDataTypeCode.BFLOAT: "bfloat",
    DLDataTypeCode.COMPLEX: "complex",
}


@dataclass(frozen=True)
class DType:
    """One DLPack element type. Only ``lanes == 1`` types are supported by this package."""

    code: int
    bits: int
    lanes: int = 1

    @property
    def name(self) -> str:
        """Canonical name (``"float32"``, ``"bfloat16"``), spelled as NumPy/torch/Warp do."""
        if self.code == DLDataTypeCode.BOOL:
            base = "bool"
        else:
            try:
                base = _PREFIX[DLDataTypeCode(self.code)] + str(self.bits)
            except (KeyError, ValueError):
                try:
                    base = DLDataTypeCode(self.code).name.lower()
                except ValueError:
                    base = f"code{self.code}_bits{self.bits}"
        return base if self.lanes == 1 else f"{base}x{self.lanes}"

    @property
    def itemsize(self) -> int:
        """Bytes per element."""
        return (self.bits * self.lanes) // 8

    def numpy_dtype(self) -> np.dtype:
        """The NumPy dtype, or :class:`UnsupportedDTypeError` (bfloat16 has none)."""
        try:
            return _NUMPY[self]
        except KeyError:
            raise UnsupportedDTypeError(
                f"NumPy has no dtype for DLPack {self.name} (code={self.code}, bits={self.bits}, "
                f"lanes={self.lanes}); use tensor_conversions.torch or tensor_conversions.warp"
            ) from None

    def __str__(self) -> str:
        return self.name


def _d(code: DLDataTypeCode, bits: int) -> DType:
    return DType(int(code), bits, 1)


#: Every dtype the package converts, by canonical name.
SUPPORTED_DTYPES: dict[str, DType] = {
    "bool": _d(DLDataTypeCode.BOOL, 8),
    **{f"int{b}": _d(DLDataTypeCode.INT, b) for b in (8, 16, 32, 64)},
    **{f"uint{b}": _d(DLDataTypeCode.UINT, b) for b in (8, 16, 32, 64)},
    **{f"float{b}": _d(DLDataTypeCode.FLOAT, b) for b in (16, 32, 64)},
    "bfloat16": _d(DLDataTypeCode.BFLOAT, 16),
    "complex64": _d(DLDataTypeCode.COMPLEX, 64),
    "complex128": _d(DLDataTypeCode.COMPLEX, 128),
}

_NUMPY: dict[DType, np.dtype] = {
    dt: np.dtype(name) for name, dt in SUPPORTED_DTYPES.items() if name != "bfloat16"
}
_BY_TRIPLE = {(dt.code, dt.bits, dt.lanes): dt for dt in SUPPORTED_DTYPES.values()}


def dtype_from_metadata(code: int, bits: int, lanes: int) -> DType:
    """Validate message metadata ``(dtype_code, dtype_bits, dtype_lanes)`` into a :class:`DType`."""
    code, bits, lanes = int(code), int(bits), int(lanes)
    found = _BY_TRIPLE.get((code, bits, lanes))
    if found is not None:
        return found
    wanted = DType(code, bits, lanes)
    if lanes != 1:
        raise UnsupportedDTypeError(
            f"dtype_lanes={lanes} ({wanted.name}): vector (multi-lane) elements are not supported, "
            "lanes must be 1"
        )
    raise UnsupportedDTypeError(
        f"unsupported DLPack dtype code={code} bits={bits} ({wanted.name}); supported: "
        + ", ".join(SUPPORTED_DTYPES)
    )


def dtype_from_name(name: str) -> DType:
    """The :class:`DType` of a canonical name such as ``"float32"`` or ``"bfloat16"``."""
    try:
        return SUPPORTED_DTYPES[name]
    except KeyError:
        raise UnsupportedDTypeError(
            f"unsupported dtype {name!r}; supported: {', '.join(SUPPORTED_DTYPES)}"
        ) from None


# perf: memo of successful dtype_from_numpy lookups, keyed by the caller's (hashable) dtype spec
# (np.uint8, "float32", np.dtype(...)); the mapping is fixed, errors are never cached.
_FROM_NUMPY: dict[object, DType] = {}


def dtype_from_numpy(dtype: object) -> DType:
    """The :class:`DType` of a NumPy dtype (or anything ``np.dtype`` accepts)."""
    try:
        return _FROM_NUMPY[dtype]
    except (KeyError, TypeError):  # not seen yet, or unhashable
        pass
    found = _dtype_from_numpy(dtype)
    try:
        _FROM_NUMPY[dtype] = found
    except TypeError:
        pass
    return found


def _dtype_from_numpy(dtype: object) -> DType:
    if dtype is None:  # np.dtype(None) is float64: a missing dtype, not a choice
        raise UnsupportedDTypeError("a dtype is needed (np.float32, 'uint8', ...), got None")
    try:
        np_dtype = np.dtype(dtype)  # type: ignore[call-overload]
    except TypeError:
        if isinstance(dtype, str) and dtype == "bfloat16":
            raise UnsupportedDTypeError(
                "NumPy has no bfloat16 dtype; use tensor_conversions.torch or "
                "tensor_conversions.warp"
            ) from None
        raise UnsupportedDTypeError(f"{dtype!r} is not a NumPy dtype") from None
    if not np_dtype.isnative:
        raise UnsupportedDTypeError(
            f"big-endian dtype {np_dtype} is not supported (DLPack is native-endian)")
    return dtype_from_name(np_dtype.name)
