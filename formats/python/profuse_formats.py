"""Validated readers and writers for the ProFuse file formats (SPEC.md): the Python
package ``profuse-formats`` (``pip install ./formats/python``), mirror of the Rust crate
``profuse-formats`` and the reference implementation for other languages.

Every ProFuse file is a safetensors container whose ``__metadata__`` names its kind
(``format = "profuse.<kind>"``) and version (``format_version = "1.x"``). This module
parses the container header itself, applying the structural checks of SPEC.md section 2
in the same order and with the same error codes as the Rust reader, then checks the
kind's metadata, tensors (presence, dtype, shape with named dimensions) and value rules,
again in the Rust order, so that any file yields the same verdict, error code and field
in both languages. Arrays are loaded with the ``safetensors`` package once the header
has been validated.

Public API::

    read_any(path)              -> the record of whatever kind the file names
    read_cameras(path) ... read_fuse_partial(path)
                                -> a dataclass of numpy arrays + metadata per kind
                                   (one reader per kind of SPEC.md section 4)
    write_cameras(path, ...) ... write_fuse_partial(path, ...)
                                -> validates numpy arrays + metadata with the reader's
                                   rules and writes the file atomically, byte for byte
                                   as the Rust writer does
    write_file(path, kind, tensors, metadata), write_record(path, record),
    encode_file(kind, tensors, metadata)
                                -> the generic writers
    inspect(path)               -> (report dict, FormatError or None), the JSON report of
                                   ``profuse inspect``; ``report_json(report)`` renders it
    open_container(path)        -> the structurally checked header (SPEC.md section 2)
    FormatError                 -> raised on every invalid or unreadable file; has
                                   ``code``, ``field``, ``path`` and a message

Command line::

    python3 profuse_formats.py inspect FILE

prints the inspect report (byte-identical to ``profuse inspect FILE``) and exits 0 for
a valid file, 1 (with ``error: <message>`` on stderr) for an invalid one.

This file depends only on ``numpy`` and ``safetensors``; it is installed by
``pip install ./formats/python`` and may also be copied into other projects as is.
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import math
import os
import re
import stat
import struct
import sys
from typing import Any, Callable, ClassVar

import numpy as np
from safetensors import SafetensorError, safe_open

__all__ = [
    "FormatError",
    "ERROR_CODES",
    "KINDS",
    "MAJOR_VERSION",
    "TensorInfo",
    "Container",
    "open_container",
    "Cameras",
    "Gaussians",
    "Masks",
    "Matches",
    "SparseMatches",
    "Proposals",
    "Features",
    "Pq",
    "Prompts",
    "Selection",
    "VertexLabels",
    "Mesh",
    "ViewMaps",
    "TopK",
    "read_cameras",
    "read_gaussians",
    "read_masks",
    "read_matches",
    "read_sparse_matches",
    "read_proposals",
    "read_features",
    "read_pq",
    "read_prompts",
    "read_selection",
    "read_vertex_labels",
    "read_mesh",
    "read_view_maps",
    "read_topk",
    "FusePartial",
    "read_fuse_partial",
    "SemanticIndex",
    "read_semantic_index",
    "quantise_share",
    "fixed_point",
    "fixed_point_words",
    "NO_GROUP",
    "WarpPartial",
    "read_warp_partial",
    "WARP_COUNTERS",
    "WARP_INPUTS",
    "write_file",
    "write_record",
    "encode_file",
    "GENERATOR",
    "write_cameras",
    "write_gaussians",
    "write_masks",
    "write_matches",
    "write_sparse_matches",
    "write_proposals",
    "write_features",
    "write_pq",
    "write_prompts",
    "write_selection",
    "write_vertex_labels",
    "write_mesh",
    "write_view_maps",
    "write_topk",
    "write_fuse_partial",
    "write_warp_partial",
    "write_semantic_index",
    "read_any",
    "inspect",
    "report_json",
    "main",
    "DTYPE_SIZES",
    "NO_PROPOSAL",
    "NO_OBJECT",
    "NO_GAUSSIAN",
]

# --------------------------------------------------------------------------------------
# Constants
# --------------------------------------------------------------------------------------

#: Major version every reader of this module accepts (SPEC.md 3.2).
MAJOR_VERSION = 1
#: Largest header accepted, as in the reference safetensors implementation.
MAX_HEADER_BYTES = 100_000_000
#: Stable machine-readable error codes (SPEC.md 3.6).
ERROR_CODES = (
    "io",
    "truncated",
    "header",
    "wrong_kind",
    "wrong_version",
    "metadata",
    "missing_tensor",
    "dtype",
    "shape",
    "out_of_range",
    "non_finite",
    "invalid",
)
#: The file kinds of SPEC.md, in SPEC.md order.
KINDS = (
    "cameras",
    "gaussians",
    "masks",
    "matches",
    "sparse_matches",
    "proposals",
    "features",
    "pq",
    "prompts",
    "selection",
    "vertex_labels",
    "mesh",
    "view_maps",
    "topk",
    "fuse_partial",
    "warp_partial",
    "semantic_index",
)

_U32_MAX = 2**32 - 1
_U64_MAX = 2**64 - 1
# serde_json refuses to nest arrays/objects this deep (its recursion limit).
_JSON_MAX_DEPTH = 128

#: Bytes per element of each container dtype.
DTYPE_SIZES = {
    "BOOL": 1,
    "U8": 1,
    "I8": 1,
    "U16": 2,
    "I16": 2,
    "U32": 4,
    "I32": 4,
    "U64": 8,
    "I64": 8,
    "F16": 2,
    "BF16": 2,
    "F32": 4,
    "F64": 8,
}

# numpy equivalents (BF16 has none; no kind allows it).
_NUMPY_DTYPES = {
    "BOOL": np.dtype(np.bool_),
    "U8": np.dtype("<u1"),
    "I8": np.dtype("<i1"),
    "U16": np.dtype("<u2"),
    "I16": np.dtype("<i2"),
    "U32": np.dtype("<u4"),
    "I32": np.dtype("<i4"),
    "U64": np.dtype("<u8"),
    "I64": np.dtype("<i8"),
    "F16": np.dtype("<f2"),
    "F32": np.dtype("<f4"),
    "F64": np.dtype("<f8"),
}

# "No mask" label values and the "no proposal" id (SPEC.md 3.4).
_LABEL_NONE = {"U16": 2**16 - 1, "U32": _U32_MAX}
NO_PROPOSAL = _U32_MAX
NO_OBJECT = _U32_MAX
#: Padding id of an unused top-K slot.
NO_GAUSSIAN = _U32_MAX
#: Slack on "sum of top-K weights + transmittance <= 1".
WEIGHT_SUM_TOLERANCE = 1e-4
#: SH coefficients per channel beyond DC for degrees 0..=3.
SH_REST_COEFFS = (0, 3, 8, 15)
#: Centroids per PQ sub-quantiser (8-bit codes).
KSUB = 256
#: Largest |R^T R - I| entry accepted for a camera rotation.
ROTATION_TOLERANCE = 1e-4
# Unit-norm tolerances per float dtype, as f32 constants widened to f64 (as in Rust).
_UNIT_NORM_TOL = {"F16": np.float32(1e-2), "F32": np.float32(1e-4)}

# --------------------------------------------------------------------------------------
# Errors
# --------------------------------------------------------------------------------------


class FormatError(Exception):
    """Why a file could not be read or validated.

    Attributes:
        code: one of :data:`ERROR_CODES` (SPEC.md 3.6).
        field: the tensor name or metadata key the error is about, or ``None``
            (``io``, ``truncated``, ``header``).
        path: the file, as given by the caller.
        message: a human-readable message naming file, field and expectation
            (the same wording as the Rust ``Display`` of ``FormatError``).
    """

    def __init__(self, code: str, path: str, message: str, field: str | None = None):
        super().__init__(message)
        self.code = code
        self.field = field
        self.path = path
        self.message = message
        #: The underlying OS error text for ``io`` errors (printed as "caused by").
        self.cause: str | None = None

    def __repr__(self) -> str:
        return f"FormatError(code={self.code!r}, field={self.field!r}, message={self.message!r})"


def _io_error(path: str, action: str, err: OSError) -> FormatError:
    detail = err.strerror or str(err)
    if err.errno is not None:
        detail = f"{detail} (os error {err.errno})"
    e = FormatError("io", path, f"{path}: {action}: {detail}")
    e.cause = detail
    return e


def _truncated(path: str, detail: str) -> FormatError:
    return FormatError("truncated", path, f"{path}: truncated: {detail}")


def _header_error(path: str, detail: str) -> FormatError:
    return FormatError("header", path, f"{path}: invalid safetensors header: {detail}")


def _wrong_kind(path: str, expected: str, found: str | None) -> FormatError:
    shown = "absent" if found is None else _debug_str(found)
    return FormatError(
        "wrong_kind", path, f'{path}: metadata `format` is {shown}, expected "{expected}"', "format"
    )


def _wrong_version(path: str, found: str | None) -> FormatError:
    shown = "absent" if found is None else _debug_str(found)
    return FormatError(
        "wrong_version",
        path,
        f'{path}: metadata `format_version` is {shown}, expected "{MAJOR_VERSION}.<minor>"',
        "format_version",
    )


def _meta_error(path: str, key: str, expected: str) -> FormatError:
    return FormatError("metadata", path, f"{path}: metadata `{key}`: expected {expected}", key)


def _missing_tensor(path: str, tensor: str, expected: str) -> FormatError:
    return FormatError(
        "missing_tensor", path, f"{path}: missing tensor `{tensor}` (expected {expected})", tensor
    )


def _dtype_error(path: str, tensor: str, found: str, expected: str) -> FormatError:
    return FormatError(
        "dtype", path, f"{path}: tensor `{tensor}` has dtype {found}, expected {expected}", tensor
    )


def _shape_error(path: str, tensor: str, found: Any, expected: str) -> FormatError:
    shown = "[" + ", ".join(str(int(d)) for d in found) + "]"
    return FormatError(
        "shape", path, f"{path}: tensor `{tensor}` has shape {shown}, expected {expected}", tensor
    )


def _out_of_range(path: str, tensor: str, index: int, value: Any, expected: str) -> FormatError:
    return FormatError(
        "out_of_range",
        path,
        f"{path}: tensor `{tensor}` element {int(index)} is {value}, expected {expected}",
        tensor,
    )


def _check_class_ids(path: str, tensor: str, values: Any, none: str) -> None:
    """Every value a class id (>= 0) or -1, which stands for `none`."""
    i = _first(values < -1)
    if i is not None:
        raise _out_of_range(path, tensor, i, int(values[i]), f"a class id >= 0 or -1 for {none}")


def _non_finite(path: str, tensor: str, index: int, value: float) -> FormatError:
    return FormatError(
        "non_finite",
        path,
        f"{path}: tensor `{tensor}` element {int(index)} is {_format_float(value)}, "
        "expected a finite value",
        tensor,
    )


def _invalid(path: str, tensor: str, detail: str) -> FormatError:
    return FormatError("invalid", path, f"{path}: tensor `{tensor}`: {detail}", tensor)


# --------------------------------------------------------------------------------------
# Text formatting shared with the Rust messages
# --------------------------------------------------------------------------------------


def _format_float(v: float) -> str:
    """Shortest round-trip text of a float as Rust's ``{:?}`` writes it, with
    ``nan``/``inf``/``-inf`` spelled as in Python (Rust ``check::format_float``)."""
    v = float(v)
    if math.isnan(v):
        return "nan"
    if math.isinf(v):
        return "inf" if v > 0 else "-inf"
    text = repr(v)
    if "e" in text:
        mantissa, exponent = text.split("e")
        text = f"{mantissa}e{int(exponent)}"
    return text


def _display_float(v: Any, dtype: str = "F32") -> str:
    """A float as Rust's ``{}`` (Display) writes it: shortest round-trip digits for its
    own precision, positional notation, no trailing ``.0``."""
    if dtype == "F64":
        x = np.float64(v)
    else:
        x = np.float32(v)
    if np.isnan(x):
        return "NaN"
    if np.isinf(x):
        return "inf" if x > 0 else "-inf"
    return np.format_float_positional(x, unique=True, trim="-")


def _debug_str(s: str) -> str:
    """A string quoted as Rust's ``{:?}`` writes it (close enough for messages)."""
    out = ['"']
    for ch in s:
        code = ord(ch)
        if ch == '"':
            out.append('\\"')
        elif ch == "\\":
            out.append("\\\\")
        elif ch == "\n":
            out.append("\\n")
        elif ch == "\r":
            out.append("\\r")
        elif ch == "\t":
            out.append("\\t")
        elif ch == "\0":
            out.append("\\0")
        elif code < 0x20 or code == 0x7F:
            out.append(f"\\u{{{code:x}}}")
        else:
            out.append(ch)
    out.append('"')
    return "".join(out)


# --------------------------------------------------------------------------------------
# JSON as serde_json reads it
# --------------------------------------------------------------------------------------


class _JsonError(ValueError):
    """JSON that serde_json (used by the Rust reader) would refuse."""


def _json_parse_int(text: str) -> Any:
    # serde_json keeps non-negative integers up to u64::MAX as integers; negative ones
    # (including -0) and larger ones are not u64 (larger ones become f64, an error when
    # they overflow to infinity). Returning a float marks "not a u64".
    value = int(text)
    if 0 <= value <= _U64_MAX and not text.startswith("-"):
        return value
    try:
        return float(value)
    except OverflowError:
        raise _JsonError("number out of range") from None


def _json_parse_float(text: str) -> float:
    value = float(text)
    if math.isinf(value):
        raise _JsonError("number out of range")
    return value


def _json_parse_constant(text: str) -> Any:
    raise _JsonError(f"{text} is not JSON")


def _json_check(value: Any) -> None:
    """Rejects what Python's json accepts but serde_json does not: nesting of 128 or
    more arrays/objects, and strings holding lone UTF-16 surrogates."""
    stack = [(value, 1)]
    while stack:
        item, depth = stack.pop()
        if isinstance(item, (dict, list)):
            if depth >= _JSON_MAX_DEPTH:
                raise _JsonError("recursion limit exceeded")
            if isinstance(item, dict):
                for k, v in item.items():
                    _json_check_str(k)
                    stack.append((v, depth + 1))
            else:
                stack.extend((v, depth + 1) for v in item)
        elif isinstance(item, str):
            _json_check_str(item)


def _json_check_str(s: str) -> None:
    try:
        s.encode("utf-8")
    except UnicodeEncodeError:
        raise _JsonError("lone leading surrogate in hex escape") from None


def _json_loads(text: str) -> Any:
    """Parses JSON exactly as strictly as serde_json; raises :class:`_JsonError`."""
    try:
        value = json.loads(
            text,
            parse_int=_json_parse_int,
            parse_float=_json_parse_float,
            parse_constant=_json_parse_constant,
        )
    except RecursionError:
        raise _JsonError("recursion limit exceeded") from None
    except _JsonError:
        raise
    except json.JSONDecodeError as e:
        raise _JsonError(f"{e.msg} at line {e.lineno} column {e.colno}") from None
    except ValueError as e:
        raise _JsonError(str(e)) from None
    _json_check(value)
    return value


def _as_u64(v: Any) -> int | None:
    """The value as a non-negative integer if serde_json's ``as_u64`` would give one."""
    if type(v) is int and 0 <= v <= _U64_MAX:
        return v
    return None


def _parse_usize(text: str) -> int | None:
    """Rust ``str::parse::<usize>``: ASCII digits with an optional leading ``+``."""
    if re.fullmatch(r"\+?[0-9]+", text, flags=re.ASCII) is None:
        return None
    value = int(text)
    return value if value <= _U64_MAX else None


def _parse_u32_decimal(text: str) -> int | None:
    """Rust ``kind::parse_decimal``: non-empty ASCII digits that fit a u32."""
    if not text or any(ch not in "0123456789" for ch in text):
        return None
    value = int(text)
    return value if value <= _U32_MAX else None


# --------------------------------------------------------------------------------------
# Container (SPEC.md 2)
# --------------------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class TensorInfo:
    """One tensor's header entry."""

    dtype: str
    shape: tuple[int, ...]
    #: Byte range relative to the start of the data section.
    data_offsets: tuple[int, int]

    @property
    def numel(self) -> int:
        """Number of scalars."""
        return math.prod(self.shape)


@dataclasses.dataclass
class Container:
    """A structurally valid safetensors file: every tensor's bytes exist and agree with
    its dtype and shape. Kind-specific validation is done by the readers."""

    #: The path as given (errors name it).
    path: str
    #: Size of the file in bytes.
    file_size: int
    #: Offset of the data section in the file (8 + header length).
    data_start: int
    #: Header entries, sorted by name.
    tensors: dict[str, TensorInfo]
    #: ``__metadata__``, sorted by key.
    metadata: dict[str, str]
    #: The path to open the file again (``path`` is its text for messages).
    fs_path: Any = None

    def __post_init__(self) -> None:
        if self.fs_path is None:
            self.fs_path = self.path

    def read_tensor_direct(self, name: str) -> np.ndarray:
        """Reads one tensor with numpy at its validated offsets (used only when the
        ``safetensors`` package refuses a header that SPEC.md allows)."""
        info = self.tensors[name]
        dtype = _NUMPY_DTYPES[info.dtype]
        try:
            arr = np.fromfile(
                self.fs_path, dtype=dtype, count=info.numel, offset=self.data_start + info.data_offsets[0]
            )
        except OSError as e:
            raise _io_error(self.path, "cannot map", e) from None
        return arr.reshape(info.shape)


def _label(path: Any) -> str:
    """The path as Rust's ``Path::display`` shows it."""
    if isinstance(path, bytes):
        return path.decode("utf-8", "replace")
    text = os.fspath(path)
    if isinstance(text, bytes):
        return text.decode("utf-8", "replace")
    try:
        text.encode("utf-8")
    except UnicodeEncodeError:
        text = os.fsencode(text).decode("utf-8", "replace")
    return text


def open_container(path: Any) -> Container:
    """Opens a file and checks its container structure (SPEC.md 2, checks 1-9).

    Raises :class:`FormatError` with code ``io``, ``truncated`` or ``header``.
    """
    return _open_container(path, _label(path))


def _foreign_format(head: bytes) -> str | None:
    """What a file given in place of a container is, from its first bytes (asked only
    once the header length has failed); mirrors ``foreign_format`` in container.rs."""
    if head.startswith(b"ply\n") or head.startswith(b"ply\r\n"):
        return "it is a PLY file; convert an INRIA 3DGS PLY with `scene-io ply-import FILE --out gaussians.safetensors`"
    if head.startswith(b"\x93NUMPY"):
        return "it is a NumPy .npy array (scene-io reads NumPy inputs: see `scene-io --help`)"
    if head.startswith(b"PK\x03\x04"):
        return "it is a zip archive such as a NumPy .npz (scene-io reads those: see `scene-io --help`)"
    return None


def _open_container(path: Any, label: str) -> Container:
    """:func:`open_container` naming the file ``label`` in errors (the writers validate
    their temporary file under the target's name)."""
    # A FIFO (or device) would block the open itself or never end: refuse it first.
    try:
        regular = stat.S_ISREG(os.stat(path).st_mode)
    except OSError as e:
        raise _io_error(label, "cannot open", e) from None
    if not regular:
        raise _io_error(label, "cannot open", OSError("not a regular file"))
    try:
        f = open(path, "rb")
    except OSError as e:
        raise _io_error(label, "cannot open", e) from None
    with f:
        try:
            file_len = os.fstat(f.fileno()).st_size
        except OSError as e:
            raise _io_error(label, "cannot stat", e) from None
        try:
            head = f.read(8)
            if file_len < 8:
                raise _truncated(label, f"{file_len} bytes, shorter than the 8-byte header length")
            (header_len,) = struct.unpack("<Q", head)
            if header_len > MAX_HEADER_BYTES:
                foreign = _foreign_format(head)
                if foreign is not None:
                    raise _header_error(label, f"not a safetensors file: {foreign}")
                raise _header_error(
                    label, f"header length {header_len} exceeds the {MAX_HEADER_BYTES}-byte limit"
                )
            if 8 + header_len > file_len:
                raise _truncated(
                    label,
                    f"header announces {header_len} bytes but the file has {file_len - 8} after the length",
                )
            raw = f.read(header_len)
        except OSError as e:
            raise _io_error(label, "cannot map", e) from None
    if len(raw) != header_len:  # the file shrank while we read it
        raise _truncated(label, f"header announces {header_len} bytes but the file has {len(raw)}")
    tensors, metadata = _parse_header(label, raw)
    _check_data_layout(label, tensors, file_len - 8 - header_len)
    return Container(
        path=label,
        file_size=file_len,
        data_start=8 + header_len,
        tensors=tensors,
        metadata=metadata,
        fs_path=path,
    )


def _parse_header(path: str, raw: bytes) -> tuple[dict[str, TensorInfo], dict[str, str]]:
    """Checks 4-7 of SPEC.md 2, in the Rust order (entries by sorted name)."""
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError as e:
        if e.reason == "unexpected end of data":
            detail = f"incomplete utf-8 byte sequence from index {e.start}"
        else:
            detail = f"invalid utf-8 sequence of {e.end - e.start} bytes from index {e.start}"
        raise _header_error(path, f"header is not UTF-8: {detail}") from None
    try:
        obj = _json_loads(text)
    except _JsonError as e:
        raise _header_error(path, f"header is not JSON: {e}") from None
    if not isinstance(obj, dict):
        raise _header_error(path, "header is not a JSON object")
    metadata: dict[str, str] = {}
    tensors: dict[str, TensorInfo] = {}
    for name in sorted(obj):
        entry = obj[name]
        if name == "__metadata__":
            if not isinstance(entry, dict):
                raise _header_error(path, "`__metadata__` is not an object")
            for key in sorted(entry):
                value = entry[key]
                if not isinstance(value, str):
                    raise _header_error(path, f"`__metadata__.{key}` is not a string")
                metadata[key] = value
            continue
        try:
            tensors[name] = _parse_entry(name, entry)
        except ValueError as e:
            raise _header_error(path, str(e)) from None
    return tensors, metadata


def _parse_entry(name: str, entry: Any) -> TensorInfo:
    """One tensor entry; raises ``ValueError`` with the detail of a ``header`` error."""
    if not isinstance(entry, dict):
        raise ValueError(f"entry `{name}` is not an object")
    dtype = entry.get("dtype")
    if not isinstance(dtype, str):
        raise ValueError(f"entry `{name}` has no string `dtype`")
    if dtype not in DTYPE_SIZES:
        raise ValueError(f"entry `{name}` has unknown dtype {_debug_str(dtype)}")
    shape_json = entry.get("shape")
    if not isinstance(shape_json, list):
        raise ValueError(f"entry `{name}` has no array `shape`")
    shape = [_as_u64(d) for d in shape_json]
    if any(d is None for d in shape):
        raise ValueError(
            f"entry `{name}` has a shape that is not a list of non-negative integers"
        )
    offsets = entry.get("data_offsets")
    pair = None
    if isinstance(offsets, list) and len(offsets) == 2:
        b, e = _as_u64(offsets[0]), _as_u64(offsets[1])
        if b is not None and e is not None:
            pair = (b, e)
    if pair is None:
        raise ValueError(f"entry `{name}` has no `data_offsets` pair of non-negative integers")
    begin, end = pair
    if begin > end:
        raise ValueError(f"entry `{name}` has data_offsets [{begin}, {end}] that decrease")
    numel = 1
    for d in shape:
        numel *= d
        if numel > _U64_MAX:
            raise ValueError(f"entry `{name}` has a shape whose size overflows")
    nbytes = numel * DTYPE_SIZES[dtype]
    if nbytes > _U64_MAX:
        raise ValueError(f"entry `{name}` has a shape whose size overflows")
    if end - begin != nbytes:
        shown = "[" + ", ".join(str(d) for d in shape) + "]"
        raise ValueError(
            f"entry `{name}` spans {end - begin} bytes but dtype {dtype} and shape {shown} need {nbytes}"
        )
    return TensorInfo(dtype=dtype, shape=tuple(shape), data_offsets=(begin, end))


def _check_data_layout(path: str, tensors: dict[str, TensorInfo], data_len: int) -> None:
    """Checks 8-9 of SPEC.md 2: the tensors tile the data section exactly."""
    spans = sorted((t.data_offsets[0], t.data_offsets[1], n) for n, t in tensors.items())
    cursor = 0
    for begin, end, name in spans:
        if begin != cursor:
            raise _header_error(
                path,
                f"tensor `{name}` starts at byte {begin} of the data, expected {cursor} (gap or overlap)",
            )
        cursor = end
    if cursor > data_len:
        raise _truncated(
            path, f"header announces {cursor} bytes of tensor data but the file has {data_len}"
        )
    if cursor < data_len:
        raise _header_error(
            path, f"{data_len - cursor} bytes after the last tensor are not described by the header"
        )


_NP_MAX_BYTES = 2**63 - 1


def _empty_array(info: TensorInfo) -> np.ndarray:
    """A tensor with no elements, made without reading the file.

    SPEC.md allows any dimension next to a 0 (``[0, 2**62]`` is a valid empty tensor), but
    numpy cannot represent a shape whose dimensions reach 2^63 or whose non-zero
    dimensions span 2^63 bytes or more (issue 20 item 2: these raised ``ValueError``).
    Such a tensor is read as an empty array of the same rank with every dimension 0; the
    header's shape stays in :attr:`Container.tensors` (and the inspect report), and the
    record's dimension fields (``dim``, ``height``, ``width``, ``k``) hold the header's
    values.
    """
    dtype = _NUMPY_DTYPES[info.dtype]
    span = dtype.itemsize
    for d in info.shape:
        span *= max(d, 1)
    if span <= _NP_MAX_BYTES:
        return np.empty(info.shape, dtype=dtype)
    return np.empty((0,) * len(info.shape), dtype=dtype)


def _load_arrays(c: Container, names: list[str]) -> dict[str, np.ndarray]:
    """Loads tensors of a validated container with the ``safetensors`` package; tensors
    with no elements are made directly (:func:`_empty_array`)."""
    arrays: dict[str, np.ndarray] = {
        n: _empty_array(c.tensors[n]) for n in names if c.tensors[n].numel == 0
    }
    names = [n for n in names if n not in arrays]
    if not names:
        return arrays
    try:
        with safe_open(os.fspath(c.fs_path), framework="np") as f:
            for name in names:
                arrays[name] = f.get_tensor(name)
    except SafetensorError:
        # safetensors refuses a few headers that SPEC.md allows (a repeated
        # `__metadata__` key); read those tensors at the offsets validated above.
        arrays = {n: a for n, a in arrays.items() if c.tensors[n].numel == 0}
    except OSError as e:
        raise _io_error(c.path, "cannot map", e) from None
    for name in names:
        info = c.tensors[name]
        arr = arrays.get(name)
        if arr is None or arr.shape != info.shape or arr.dtype != _NUMPY_DTYPES[info.dtype]:
            arrays[name] = c.read_tensor_direct(name)
    return arrays


# --------------------------------------------------------------------------------------
# Kind, version and the tensor reader with named dimensions
# --------------------------------------------------------------------------------------


def _format_name(kind: str) -> str:
    return f"profuse.{kind}"


_KIND_BY_FORMAT = {_format_name(k): k for k in KINDS}


def _check_version(c: Container) -> None:
    """``format_version`` must read ``MAJOR.MINOR`` with MAJOR = 1 (Rust ``check_version``)."""
    found = c.metadata.get("format_version")
    ok = False
    if found is not None:
        parts = found.split(".")
        ok = (
            len(parts) == 2
            and _parse_u32_decimal(parts[0]) == MAJOR_VERSION
            and _parse_u32_decimal(parts[1]) is not None
        )
    if not ok:
        raise _wrong_version(c.path, found)


def _check_kind(c: Container, kind: str) -> None:
    """``format`` must name ``kind``, then the version is checked."""
    found = c.metadata.get("format")
    if found != _format_name(kind):
        raise _wrong_kind(c.path, _format_name(kind), found)
    _check_version(c)


class _Reader:
    """Checks one container's metadata and tensors (presence, dtype, shape), binding
    named dimensions on first use and checking every later use (Rust ``TensorReader``).
    Records which tensors to load."""

    def __init__(self, c: Container):
        self.c = c
        self.path = c.path
        self.dims: dict[str, tuple[int, str]] = {}
        self.names: list[str] = []

    # -- dimensions ---------------------------------------------------------------

    def bind(self, sym: str, value: int, source: str) -> None:
        """Binds a dimension from metadata or another source before tensors use it."""
        self.dims[sym] = (value, source)

    def dim(self, sym: str) -> int:
        """A bound dimension, 0 if unbound."""
        return self.dims.get(sym, (0, ""))[0]

    def check_shape(self, name: str, pattern: str) -> None:
        """Checks a tensor's shape against a pattern like ``"N,3"`` (names bind on first
        use, digits are fixed) and binds new names once the whole shape matched."""
        info = self._info(name, f"shape [{pattern}]")
        parts = [p.strip() for p in pattern.split(",")]
        if len(info.shape) != len(parts):
            raise self._shape_mismatch(name, info.shape, parts)
        fresh: dict[str, int] = {}
        for part, d in zip(parts, info.shape):
            fixed = _parse_usize(part)
            if fixed is not None:
                expected = fixed
            elif part in self.dims:
                expected = self.dims[part][0]
            elif part in fresh:
                expected = fresh[part]
            else:
                fresh[part] = d
                continue
            if expected != d:
                raise self._shape_mismatch(name, info.shape, parts)
        for sym, d in fresh.items():
            self.dims[sym] = (d, name)

    def _shape_mismatch(self, name: str, found: tuple[int, ...], parts: list[str]) -> FormatError:
        shown = []
        for p in parts:
            if p in self.dims:
                value, source = self.dims[p]
                shown.append(f"{p}={value} (from {source})")
            else:
                shown.append(p)
        return _shape_error(self.path, name, found, "[" + ", ".join(shown) + "]")

    # -- tensors --------------------------------------------------------------------

    def _info(self, name: str, expected: str) -> TensorInfo:
        info = self.c.tensors.get(name)
        if info is None:
            raise _missing_tensor(self.path, name, expected)
        return info

    def has(self, name: str) -> bool:
        """Whether the header has this tensor."""
        return name in self.c.tensors

    def req(self, name: str, dtype: str, pattern: str, lanes: int = 1) -> None:
        """A required tensor of one dtype. ``lanes`` is the row length the Rust reader
        views the data as (e.g. 3 for points), checked before the shape."""
        info = self._info(name, dtype)
        if info.dtype != dtype:
            raise _dtype_error(self.path, name, info.dtype, dtype)
        if info.numel % lanes != 0:
            raise _shape_error(self.path, name, info.shape, f"a last dimension of {lanes}")
        self.check_shape(name, pattern)
        self.names.append(name)

    def opt(self, name: str, dtype: str, pattern: str, lanes: int = 1) -> bool:
        """An optional tensor: absent is fine, present must be right."""
        if not self.has(name):
            return False
        self.req(name, dtype, pattern, lanes)
        return True

    def req_either(self, name: str, allowed: tuple[str, str], pattern: str) -> str:
        """A required tensor of one of two dtypes (F16/F32 floats, U16/U32 labels)."""
        expected = f"{allowed[0]} or {allowed[1]}"
        info = self._info(name, f"dtype {expected}")
        if info.dtype not in allowed:
            raise _dtype_error(self.path, name, info.dtype, expected)
        self.check_shape(name, pattern)
        self.names.append(name)
        return info.dtype

    # -- metadata -------------------------------------------------------------------

    def meta(self, key: str, expected: str) -> str:
        """A required metadata string."""
        value = self.c.metadata.get(key)
        if value is None:
            raise _meta_error(self.path, key, expected)
        return value

    def meta_usize(self, key: str, expected: str) -> int:
        """A metadata value parsed as a Rust ``usize``."""
        value = _parse_usize(self.meta(key, expected))
        if value is None:
            raise _meta_error(self.path, key, expected)
        return value

    def meta_strings(self, key: str) -> list[str]:
        """A metadata value holding a JSON array of strings."""
        expected = "a JSON array of strings"
        raw = self.meta(key, expected)
        try:
            value = _json_loads(raw)
        except _JsonError:
            raise _meta_error(self.path, key, expected) from None
        if not isinstance(value, list) or not all(isinstance(v, str) for v in value):
            raise _meta_error(self.path, key, expected)
        return value

    def load(self) -> dict[str, np.ndarray]:
        """Loads every tensor checked so far."""
        return _load_arrays(self.c, self.names)


# --------------------------------------------------------------------------------------
# Value checks (Rust check.rs); each reports the first failing element
# --------------------------------------------------------------------------------------


def _first(mask: np.ndarray) -> int | None:
    """Index of the first True of a flat boolean array, or None."""
    if mask.size == 0:
        return None
    i = int(np.argmax(mask))
    return i if mask[i] else None


def _check_finite(path: str, tensor: str, arr: np.ndarray) -> None:
    """Every value finite."""
    flat = arr.reshape(-1)
    i = _first(~np.isfinite(flat))
    if i is not None:
        raise _non_finite(path, tensor, i, float(flat[i]))


def _check_unit_interval(path: str, tensor: str, arr: np.ndarray) -> None:
    """Every value finite and in [0, 1] (compared as f32)."""
    _check_finite(path, tensor, arr)
    flat = arr.reshape(-1).astype(np.float32, copy=False)
    i = _first(~((flat >= 0) & (flat <= 1)))
    if i is not None:
        raise _out_of_range(path, tensor, i, _format_float(float(flat[i])), "a value in [0, 1]")


def _check_ids(
    path: str, tensor: str, arr: np.ndarray, limit: int, none: int | None, what: str
) -> None:
    """Every index ``< limit``, except the reserved ``none`` value when given."""
    flat = arr.reshape(-1).astype(np.uint64, copy=False)
    bad = flat >= np.uint64(limit)
    if none is not None:
        bad &= flat != np.uint64(none)
    i = _first(bad)
    if i is not None:
        if none is not None:
            expected = f"an index < {limit} into {what} or the reserved {none}"
        else:
            expected = f"an index < {limit} into {what}"
        raise _out_of_range(path, tensor, i, int(flat[i]), expected)


def _check_offsets(path: str, tensor: str, arr: np.ndarray, total: int) -> None:
    """CSR offsets: start at 0, never decrease, end at ``total``."""
    off = arr.reshape(-1).astype(np.uint64, copy=False)
    if off.size and off[0] != 0:
        raise _out_of_range(path, tensor, 0, int(off[0]), "0")
    i = _first(off[1:] < off[:-1])
    if i is not None:
        prev = int(off[i])
        raise _out_of_range(
            path, tensor, i + 1, int(off[i + 1]), f"a value >= {prev} (offsets never decrease)"
        )
    last = int(off[-1]) if off.size else 0
    if last != total:
        raise _out_of_range(
            path, tensor, max(off.size - 1, 0), last, f"the last offset to equal {total}"
        )


def _check_flags(path: str, tensor: str, arr: np.ndarray) -> None:
    """Flags that are 0 or 1."""
    i = _first(arr > 1)
    if i is not None:
        raise _out_of_range(path, tensor, i, int(arr[i]), "0 or 1")


def _row_norms(rows: np.ndarray) -> np.ndarray:
    """L2 norms of the rows, summing squares in f64 left to right as Rust does (numpy's
    pairwise ``sum`` would round differently; ``cumsum`` is sequential)."""
    n, dim = rows.shape
    norms = np.empty(n, dtype=np.float64)
    chunk = max(1, (1 << 22) // max(dim, 1))
    for start in range(0, n, chunk):
        x = rows[start : start + chunk].astype(np.float32).astype(np.float64)
        norms[start : start + chunk] = np.sqrt(np.cumsum(x * x, axis=1)[:, -1])
    return norms


def _check_unit_rows(
    path: str, tensor: str, arr: np.ndarray, dtype: str, zero_rows: np.ndarray | None
) -> None:
    """Each row has unit L2 norm within the dtype's tolerance; rows where ``zero_rows``
    is True must instead be all zero."""
    rows, dim = arr.shape
    if dim == 0 or rows == 0:
        return
    tol32 = _UNIT_NORM_TOL[dtype]
    tol = float(tol32)
    norms = _row_norms(arr)
    zero = np.zeros(rows, dtype=bool) if zero_rows is None else zero_rows.astype(bool)
    bad = np.where(zero, norms != 0.0, np.abs(norms - 1.0) > tol)
    r = _first(bad)
    if r is None:
        return
    norm = float(norms[r])
    if zero[r]:
        raise _invalid(
            path,
            tensor,
            f"row {r} is marked invalid but is not all zero (norm {_format_float(norm)})",
        )
    raise _invalid(
        path,
        tensor,
        f"row {r} has L2 norm {_format_float(norm)}, expected 1 within {_display_float(tol32)}",
    )


def _check_pairs(path: str, pairs: np.ndarray, num_views: int) -> None:
    """View ids inside the camera set, i != j, and each ordered pair at most once."""
    p = pairs.reshape(-1, 2).astype(np.uint64)
    n = p.shape[0]
    if n == 0:
        return
    range_bad = p >= np.uint64(num_views)
    self_bad = p[:, 0] == p[:, 1]
    keys = (p[:, 0] << np.uint64(32)) | p[:, 1]
    _, first_idx, inverse = np.unique(keys, return_index=True, return_inverse=True)
    dup_bad = first_idx[inverse.reshape(-1)] != np.arange(n)
    row = _first(range_bad.any(axis=1) | self_bad | dup_bad)
    if row is None:
        return
    i, j = int(p[row, 0]), int(p[row, 1])
    for k, v in enumerate((i, j)):
        if range_bad[row, k]:
            raise _out_of_range(
                path, "pairs", 2 * row + k, v, f"a view index < {num_views} (metadata num_views)"
            )
    if self_bad[row]:
        raise _invalid(path, "pairs", f"row {row} pairs view {i} with itself")
    raise _invalid(path, "pairs", f"row {row} repeats the ordered pair ({i}, {j})")


# --------------------------------------------------------------------------------------
# Records
# --------------------------------------------------------------------------------------


@dataclasses.dataclass
class _Record:
    """Base of the per-kind records: the file's path and full ``__metadata__``."""

    KIND: ClassVar[str] = ""
    #: Tensor names of the kind in table order (required and optional).
    TENSORS: ClassVar[tuple[str, ...]] = ()

    def arrays(self) -> dict[str, np.ndarray]:
        """The kind's tensors present in the file, by name."""
        out = {}
        for name in self.TENSORS:
            value = getattr(self, name)
            if value is not None:
                out[name] = value
        return out

    def counts(self) -> dict[str, int]:  # pragma: no cover - overridden
        """Counts reported by ``inspect`` (SPEC.md lists them per kind)."""
        raise NotImplementedError


@dataclasses.dataclass
class Cameras(_Record):
    """``profuse.cameras``: posed pinhole views (OpenCV, world-to-camera)."""

    KIND: ClassVar[str] = "cameras"
    TENSORS: ClassVar[tuple[str, ...]] = ("image_size", "intrinsics", "world_to_camera", "distortion")

    path: str
    metadata: dict[str, str]
    #: Image path of each view (metadata ``image_names``).
    image_names: list[str]
    #: U32 [V, 2]: width, height in pixels.
    image_size: np.ndarray
    #: F64 [V, 4]: fx, fy, cx, cy.
    intrinsics: np.ndarray
    #: F64 [V, 3, 4]: ``[R | t]``, x_cam = R x_world + t.
    world_to_camera: np.ndarray
    #: F64 [V, 4]: OpenCV k1, k2, p1, p2, or None (pinhole).
    distortion: np.ndarray | None

    def counts(self) -> dict[str, int]:
        return {"views": len(self.image_names), "distorted": int(self.distortion is not None)}


@dataclasses.dataclass
class Gaussians(_Record):
    """``profuse.gaussians``: 3D Gaussians in the INRIA 3DGS parameterisation."""

    KIND: ClassVar[str] = "gaussians"
    TENSORS: ClassVar[tuple[str, ...]] = (
        "means",
        "sh_rest",
        "log_scales",
        "rotations",
        "opacity_logits",
        "sh_dc",
        "class_ids",
    )

    path: str
    metadata: dict[str, str]
    #: SH degree 0..=3 (metadata ``sh_degree``).
    sh_degree: int
    #: F32 [N, 3].
    means: np.ndarray
    #: F32 [N, R, 3] with R = 3, 8, 15 for degree 1, 2, 3; None for degree 0.
    sh_rest: np.ndarray | None
    #: F32 [N, 3]: natural log of the per-axis standard deviations.
    log_scales: np.ndarray
    #: F32 [N, 4]: quaternion (w, x, y, z), not necessarily unit.
    rotations: np.ndarray
    #: F32 [N].
    opacity_logits: np.ndarray
    #: F32 [N, 3].
    sh_dc: np.ndarray
    #: I32 [N] or None: ground-truth class, -1 = none.
    class_ids: np.ndarray | None

    def counts(self) -> dict[str, int]:
        return {"gaussians": int(self.means.shape[0]), "sh_degree": self.sh_degree}


@dataclasses.dataclass
class Masks(_Record):
    """``profuse.masks``: per-view label maps of view-local mask indices plus one
    feature per global mask."""

    KIND: ClassVar[str] = "masks"
    TENSORS: ClassVar[tuple[str, ...]] = ("labels", "mask_offsets", "features")

    path: str
    metadata: dict[str, str]
    #: Metadata ``view_names``.
    view_names: list[str]
    #: U16 or U32 [V, H, W]; the dtype's maximum means "no mask".
    labels: np.ndarray
    #: U32 [V + 1]: view v owns global masks ``mask_offsets[v]..mask_offsets[v+1]``.
    mask_offsets: np.ndarray
    #: F16 or F32 [M, D], unit rows.
    features: np.ndarray
    height: int
    width: int
    #: Feature dimension D.
    dim: int

    @property
    def num_masks(self) -> int:
        """Total number of masks M."""
        return int(self.mask_offsets[-1]) if self.mask_offsets.size else 0

    def counts(self) -> dict[str, int]:
        return {
            "views": len(self.view_names),
            "masks": self.num_masks,
            "height": self.height,
            "width": self.width,
            "feature_dim": self.dim,
        }


@dataclasses.dataclass
class Matches(_Record):
    """``profuse.matches``: dense warps for ordered view pairs."""

    KIND: ClassVar[str] = "matches"
    TENSORS: ClassVar[tuple[str, ...]] = ("pairs", "warp", "certainty")

    path: str
    metadata: dict[str, str]
    #: Metadata ``num_views``.
    num_views: int
    #: Metadata ``coords``: ``normalized`` or ``pixels``.
    coords: str
    #: U32 [P, 2]: (i, j).
    pairs: np.ndarray
    #: F16 or F32 [P, H, W, 2]: target (x, y) in view j.
    warp: np.ndarray
    #: F16 or F32 [P, H, W] in [0, 1].
    certainty: np.ndarray
    height: int
    width: int

    def counts(self) -> dict[str, int]:
        return {
            "views": self.num_views,
            "pairs": int(self.pairs.shape[0]),
            "height": self.height,
            "width": self.width,
        }


@dataclasses.dataclass
class SparseMatches(_Record):
    """``profuse.sparse_matches``: pixel-pair matches for ordered view pairs."""

    KIND: ClassVar[str] = "sparse_matches"
    TENSORS: ClassVar[tuple[str, ...]] = ("pairs", "pair_offsets", "points_i", "points_j", "certainty")

    path: str
    metadata: dict[str, str]
    #: Metadata ``num_views``.
    num_views: int
    #: U32 [P, 2].
    pairs: np.ndarray
    #: U64 [P + 1]: pair p owns matches ``pair_offsets[p]..pair_offsets[p+1]``.
    pair_offsets: np.ndarray
    #: F32 [N, 2]: pixel (x, y) in view i.
    points_i: np.ndarray
    #: F32 [N, 2]: pixel (x, y) in view j.
    points_j: np.ndarray
    #: F32 [N] in [0, 1].
    certainty: np.ndarray

    def counts(self) -> dict[str, int]:
        return {
            "views": self.num_views,
            "pairs": int(self.pairs.shape[0]),
            "matches": int(self.points_i.shape[0]),
        }


@dataclasses.dataclass
class Proposals(_Record):
    """``profuse.proposals``: the proposal of every mask plus per-proposal counts."""

    KIND: ClassVar[str] = "proposals"
    TENSORS: ClassVar[tuple[str, ...]] = (
        "mask_proposal",
        "proposal_size",
        "proposal_views",
        "mask_share",
        "mask_instance",
    )

    path: str
    metadata: dict[str, str]
    #: U32 [M]: proposal id of each global mask, or 4294967295 (none).
    mask_proposal: np.ndarray
    #: U32 [P].
    proposal_size: np.ndarray
    #: U32 [P].
    proposal_views: np.ndarray
    #: F32 [M], each in (0, 1], or None: the estimated share of each mask on one object.
    mask_share: np.ndarray | None = None
    #: U32 [M] or None: the object instance (proposal id) of each mask: its proposal for
    #: a member, for a mask in no proposal the proposal holding most of its area, or
    #: 4294967295 (none).
    mask_instance: np.ndarray | None = None

    def instances(self) -> np.ndarray:
        """``mask_instance`` when present, otherwise ``mask_proposal``."""
        return self.mask_instance if self.mask_instance is not None else self.mask_proposal

    def counts(self) -> dict[str, int]:
        return {
            "masks": int(self.mask_proposal.shape[0]),
            "proposals": int(self.proposal_size.shape[0]),
            "assigned_masks": int(np.count_nonzero(self.mask_proposal != NO_PROPOSAL)),
        }


@dataclasses.dataclass
class Features(_Record):
    """``profuse.features``: one language descriptor per Gaussian."""

    KIND: ClassVar[str] = "features"
    TENSORS: ClassVar[tuple[str, ...]] = ("features", "valid", "weight_sum")

    path: str
    metadata: dict[str, str]
    #: F16 or F32 [N, D]: unit rows where valid, zero rows where not.
    features: np.ndarray
    #: U8 [N]: 1 = registered.
    valid: np.ndarray
    #: F32 [N] or None.
    weight_sum: np.ndarray | None
    #: Feature dimension D.
    dim: int

    def counts(self) -> dict[str, int]:
        return {
            "gaussians": int(self.valid.shape[0]),
            "feature_dim": self.dim,
            "valid": int(np.count_nonzero(self.valid == 1)),
        }


@dataclasses.dataclass
class Pq(_Record):
    """``profuse.pq``: a product quantiser (faiss layout) and the codes of N vectors."""

    KIND: ClassVar[str] = "pq"
    TENSORS: ClassVar[tuple[str, ...]] = ("centroids", "codes", "norms", "valid")

    path: str
    metadata: dict[str, str]
    #: F32 [M, 256, dsub].
    centroids: np.ndarray
    #: U8 [N, M].
    codes: np.ndarray
    #: F32 [N].
    norms: np.ndarray
    #: U8 [N].
    valid: np.ndarray
    #: Sub-quantisers M.
    m: int
    #: Sub-vector dimension.
    dsub: int

    def counts(self) -> dict[str, int]:
        return {
            "vectors": int(self.valid.shape[0]),
            "dim": self.m * self.dsub,
            "m": self.m,
            "ksub": KSUB,
            "valid": int(np.count_nonzero(self.valid == 1)),
        }


@dataclasses.dataclass
class Prompts(_Record):
    """``profuse.prompts``: named text embeddings."""

    KIND: ClassVar[str] = "prompts"
    TENSORS: ClassVar[tuple[str, ...]] = ("embeddings", "class_ids")

    path: str
    metadata: dict[str, str]
    #: Metadata ``names``: unique, non-empty.
    names: list[str]
    #: F32 [Q, D].
    embeddings: np.ndarray
    #: I32 [Q] or None.
    class_ids: np.ndarray | None
    #: Embedding dimension D.
    dim: int

    def counts(self) -> dict[str, int]:
        return {"prompts": len(self.names), "dim": self.dim}


@dataclasses.dataclass
class Selection(_Record):
    """``profuse.selection``: the Gaussians a query selected."""

    KIND: ClassVar[str] = "selection"
    TENSORS: ClassVar[tuple[str, ...]] = ("gaussian_ids", "scores")

    path: str
    metadata: dict[str, str]
    #: Metadata ``prompt``.
    prompt: str
    #: Metadata ``num_gaussians``.
    num_gaussians: int
    #: U32 [S], strictly increasing.
    gaussian_ids: np.ndarray
    #: F32 [S].
    scores: np.ndarray

    def counts(self) -> dict[str, int]:
        return {"selected": int(self.gaussian_ids.shape[0]), "gaussians": self.num_gaussians}


@dataclasses.dataclass
class VertexLabels(_Record):
    """``profuse.vertex_labels``: a predicted class per mesh vertex."""

    KIND: ClassVar[str] = "vertex_labels"
    TENSORS: ClassVar[tuple[str, ...]] = ("labels", "confidence")

    path: str
    metadata: dict[str, str]
    #: I32 [V], -1 = no label.
    labels: np.ndarray
    #: F32 [V] in [0, 1], or None.
    confidence: np.ndarray | None

    def counts(self) -> dict[str, int]:
        return {
            "vertices": int(self.labels.shape[0]),
            "labelled": int(np.count_nonzero(self.labels >= 0)),
        }


@dataclasses.dataclass
class Mesh(_Record):
    """``profuse.mesh``: a triangle mesh or point cloud with optional labels."""

    KIND: ClassVar[str] = "mesh"
    TENSORS: ClassVar[tuple[str, ...]] = ("vertices", "colors", "faces", "labels", "instances")

    path: str
    metadata: dict[str, str]
    #: F32 [V, 3].
    vertices: np.ndarray
    #: U8 [V, 3] or None.
    colors: np.ndarray | None
    #: U32 [F, 3] or None.
    faces: np.ndarray | None
    #: U32 [V] or None, 0 = unannotated.
    labels: np.ndarray | None
    #: U32 [V] or None, 0 = none.
    instances: np.ndarray | None

    def counts(self) -> dict[str, int]:
        return {
            "vertices": int(self.vertices.shape[0]),
            "faces": 0 if self.faces is None else int(self.faces.shape[0]),
            "labelled": 0 if self.labels is None else int(np.count_nonzero(self.labels != 0)),
        }


@dataclasses.dataclass
class ViewMaps(_Record):
    """``profuse.view_maps``: per-view depth and object-id maps on one grid."""

    KIND: ClassVar[str] = "view_maps"
    TENSORS: ClassVar[tuple[str, ...]] = ("depth", "object_ids")

    path: str
    metadata: dict[str, str]
    #: Metadata ``view_names``.
    view_names: list[str]
    #: Metadata ``num_objects``.
    num_objects: int
    #: F32 [V, H, W]: camera-space z, 0 = no surface.
    depth: np.ndarray
    #: U32 [V, H, W] or None: object id, 4294967295 = none.
    object_ids: np.ndarray | None
    height: int
    width: int

    def counts(self) -> dict[str, int]:
        return {
            "views": len(self.view_names),
            "height": self.height,
            "width": self.width,
            "objects": self.num_objects,
        }


# --------------------------------------------------------------------------------------
# Per-kind readers: structure (Rust from_container) then values (Rust validate)
# --------------------------------------------------------------------------------------


def _cameras(c: Container) -> Cameras:
    r = _Reader(c)
    names = r.meta_strings("image_names")
    r.bind("V", len(names), "metadata `image_names`")
    r.req("image_size", "U32", "V,2", lanes=2)
    r.req("intrinsics", "F64", "V,4", lanes=4)
    r.req("world_to_camera", "F64", "V,3,4", lanes=12)
    r.opt("distortion", "F64", "V,4", lanes=4)
    a = r.load()
    path = c.path
    for i, name in enumerate(names):
        if not name:
            raise _meta_error(path, "image_names", f"non-empty names (entry {i} is empty)")
    size = a["image_size"]
    row = _first((size == 0).any(axis=1))
    if row is not None:
        w, h = int(size[row, 0]), int(size[row, 1])
        raise _out_of_range(path, "image_size", row, f"{w}x{h}", "a width and height >= 1")
    intr = a["intrinsics"]
    _check_finite(path, "intrinsics", intr)
    focal = intr[:, :2]
    k = _first((focal <= 0.0).reshape(-1))
    if k is not None:
        i, j = divmod(k, 2)
        raise _out_of_range(
            path, "intrinsics", i * 4 + j, _display_float(focal[i, j], "F64"), "a focal length > 0"
        )
    w2c = a["world_to_camera"]
    _check_finite(path, "world_to_camera", w2c)
    _check_rotations(path, w2c)
    if "distortion" in a:
        _check_finite(path, "distortion", a["distortion"])
    return Cameras(
        path=path,
        metadata=dict(c.metadata),
        image_names=names,
        image_size=size,
        intrinsics=intr,
        world_to_camera=w2c,
        distortion=a.get("distortion"),
    )


def _check_rotations(path: str, w2c: np.ndarray) -> None:
    """Per view: every entry of RᵀR − I within 1e-4 (i, j row-major), then det R > 0.
    Products and sums are evaluated in the Rust order so results agree bit for bit."""
    if w2c.shape[0] == 0:
        return
    with np.errstate(all="ignore"):  # huge finite entries overflow, as in Rust
        _check_rotations_ieee(path, w2c)


def _check_rotations_ieee(path: str, w2c: np.ndarray) -> None:
    r = w2c[:, :, :3].astype(np.float64)
    ortho_bad = np.zeros((r.shape[0], 3, 3), dtype=bool)
    dots = np.zeros((r.shape[0], 3, 3), dtype=np.float64)
    for i in range(3):
        for j in range(3):
            dot = r[:, 0, i] * r[:, 0, j]
            dot = dot + r[:, 1, i] * r[:, 1, j]
            dot = dot + r[:, 2, i] * r[:, 2, j]
            want = 1.0 if i == j else 0.0
            dots[:, i, j] = dot
            ortho_bad[:, i, j] = np.abs(dot - want) > ROTATION_TOLERANCE
    det = (
        r[:, 0, 0] * (r[:, 1, 1] * r[:, 2, 2] - r[:, 1, 2] * r[:, 2, 1])
        - r[:, 0, 1] * (r[:, 1, 0] * r[:, 2, 2] - r[:, 1, 2] * r[:, 2, 0])
        + r[:, 0, 2] * (r[:, 1, 0] * r[:, 2, 1] - r[:, 1, 1] * r[:, 2, 0])
    )
    view_bad = ortho_bad.reshape(-1, 9).any(axis=1) | (det <= 0.0)
    v = _first(view_bad)
    if v is None:
        return
    k = _first(ortho_bad[v].reshape(-1))
    if k is not None:
        i, j = divmod(k, 3)
        raise _invalid(
            path,
            "world_to_camera",
            f"view {v}: rotation is not orthonormal (RᵀR[{i}][{j}] = {dots[v, i, j]:.6f}, "
            f"tolerance {ROTATION_TOLERANCE})",
        )
    raise _invalid(
        path,
        "world_to_camera",
        f"view {v}: rotation has determinant {det[v]:.6f}, expected +1 (a reflection)",
    )


def _gaussians(c: Container) -> Gaussians:
    r = _Reader(c)
    expected = "an integer 0, 1, 2 or 3"
    degree = r.meta_usize("sh_degree", expected)
    if degree > 3:
        raise _meta_error(c.path, "sh_degree", expected)
    r.req("means", "F32", "N,3", lanes=3)
    if degree > 0:
        r.req("sh_rest", "F32", f"N,{SH_REST_COEFFS[degree]},3")
    elif r.has("sh_rest"):
        raise _meta_error(c.path, "sh_degree", "a degree >= 1 when tensor `sh_rest` is present")
    r.req("log_scales", "F32", "N,3", lanes=3)
    r.req("rotations", "F32", "N,4", lanes=4)
    r.req("opacity_logits", "F32", "N")
    r.req("sh_dc", "F32", "N,3", lanes=3)
    r.opt("class_ids", "I32", "N")
    a = r.load()
    path = c.path
    if "sh_rest" in a:
        _check_finite(path, "sh_rest", a["sh_rest"])
    for name in ("means", "log_scales", "rotations", "opacity_logits", "sh_dc"):
        _check_finite(path, name, a[name])
    i = _first((a["rotations"] == 0.0).all(axis=1))
    if i is not None:
        raise _invalid(path, "rotations", f"row {i} is the zero quaternion")
    ids = a.get("class_ids")
    if ids is not None:
        _check_class_ids(path, "class_ids", ids, "none")
    return Gaussians(
        path=path,
        metadata=dict(c.metadata),
        sh_degree=degree,
        means=a["means"],
        sh_rest=a.get("sh_rest"),
        log_scales=a["log_scales"],
        rotations=a["rotations"],
        opacity_logits=a["opacity_logits"],
        sh_dc=a["sh_dc"],
        class_ids=ids,
    )


def _masks(c: Container) -> Masks:
    r = _Reader(c)
    names = r.meta_strings("view_names")
    r.bind("V", len(names), "metadata `view_names`")
    label_dtype = r.req_either("labels", ("U16", "U32"), "V,H,W")
    r.bind("V+1", len(names) + 1, "metadata `view_names` + 1")
    r.req("mask_offsets", "U32", "V+1")
    feat_dtype = r.req_either("features", ("F16", "F32"), "M,D")
    height, width, dim = r.dim("H"), r.dim("W"), r.dim("D")
    a = r.load()
    path = c.path
    if dim == 0:
        raise _shape_error(path, "features", [0, 0], "[M, D] with D >= 1")
    features = a["features"]
    m = features.shape[0]
    offsets = a["mask_offsets"]
    _check_offsets(path, "mask_offsets", offsets, m)
    none = _LABEL_NONE[label_dtype]
    labels = a["labels"]
    plane = height * width
    # With no view the plane is never indexed (H x W may then exceed what numpy can shape).
    flat_labels = labels.reshape(len(names), plane) if names else labels
    for view in range(len(names)):
        count = int(offsets[view + 1]) - int(offsets[view])
        if count > none:
            raise _out_of_range(
                path,
                "mask_offsets",
                view + 1,
                int(offsets[view + 1]),
                f"at most {none} masks per view for {label_dtype} labels",
            )
        values = flat_labels[view]
        i = _first((values != none) & (values.astype(np.uint64) >= np.uint64(count)))
        if i is not None:
            raise _out_of_range(
                path,
                "labels",
                view * plane + i,
                int(values[i]),
                f"a mask index < {count} of this view or the reserved {none}",
            )
    _check_finite(path, "features", features)
    _check_unit_rows(path, "features", features, feat_dtype, None)
    return Masks(
        path=path,
        metadata=dict(c.metadata),
        view_names=names,
        labels=labels,
        mask_offsets=offsets,
        features=features,
        height=height,
        width=width,
        dim=dim,
    )


def _matches(c: Container) -> Matches:
    r = _Reader(c)
    num_views = r.meta_usize("num_views", "a non-negative integer")
    coords_expected = '"normalized" or "pixels"'
    coords = r.meta("coords", coords_expected)
    if coords not in ("normalized", "pixels"):
        raise _meta_error(c.path, "coords", coords_expected)
    r.req("pairs", "U32", "P,2", lanes=2)
    r.req_either("warp", ("F16", "F32"), "P,H,W,2")
    r.req_either("certainty", ("F16", "F32"), "P,H,W")
    height, width = r.dim("H"), r.dim("W")
    a = r.load()
    path = c.path
    _check_pairs(path, a["pairs"], num_views)
    _check_finite(path, "warp", a["warp"])
    _check_unit_interval(path, "certainty", a["certainty"])
    return Matches(
        path=path,
        metadata=dict(c.metadata),
        num_views=num_views,
        coords=coords,
        pairs=a["pairs"],
        warp=a["warp"],
        certainty=a["certainty"],
        height=height,
        width=width,
    )


def _sparse_matches(c: Container) -> SparseMatches:
    r = _Reader(c)
    num_views = r.meta_usize("num_views", "a non-negative integer")
    r.req("pairs", "U32", "P,2", lanes=2)
    r.bind("P+1", c.tensors["pairs"].numel // 2 + 1, "tensor `pairs` rows + 1")
    r.req("pair_offsets", "U64", "P+1")
    r.req("points_i", "F32", "N,2", lanes=2)
    r.req("points_j", "F32", "N,2", lanes=2)
    r.req("certainty", "F32", "N")
    a = r.load()
    path = c.path
    n = a["points_i"].shape[0]
    _check_pairs(path, a["pairs"], num_views)
    _check_offsets(path, "pair_offsets", a["pair_offsets"], n)
    _check_finite(path, "points_i", a["points_i"])
    _check_finite(path, "points_j", a["points_j"])
    _check_unit_interval(path, "certainty", a["certainty"])
    return SparseMatches(
        path=path,
        metadata=dict(c.metadata),
        num_views=num_views,
        pairs=a["pairs"],
        pair_offsets=a["pair_offsets"],
        points_i=a["points_i"],
        points_j=a["points_j"],
        certainty=a["certainty"],
    )


def _proposals(c: Container) -> Proposals:
    r = _Reader(c)
    r.req("mask_proposal", "U32", "M")
    r.req("proposal_size", "U32", "P")
    r.req("proposal_views", "U32", "P")
    has_share = r.opt("mask_share", "F32", "M")
    has_instance = r.opt("mask_instance", "U32", "M")
    a = r.load()
    path = c.path
    mp, size, views = a["mask_proposal"], a["proposal_size"], a["proposal_views"]
    p = size.shape[0]
    _check_ids(path, "mask_proposal", mp, p, NO_PROPOSAL, "the proposals")
    share = a["mask_share"] if has_share else None
    if share is not None:
        _check_share(path, "mask_share", share)
    instance = a["mask_instance"] if has_instance else None
    if instance is not None:
        _check_ids(path, "mask_instance", instance, p, NO_PROPOSAL, "the proposals")
        m = _first((mp != NO_PROPOSAL) & (instance != mp))
        if m is not None:
            raise _invalid(
                path,
                "mask_instance",
                f"mask {m} is a member of proposal {int(mp[m])} but its instance is {int(instance[m])}",
            )
    members = np.bincount(mp[mp != NO_PROPOSAL].astype(np.int64), minlength=p)[:p]
    size64 = size.astype(np.int64)
    views64 = views.astype(np.int64)
    size_bad = size64 != members
    empty = size64 == 0
    views_bad = (views64 == 0) | (views64 > size64)
    i = _first(size_bad | empty | views_bad)
    if i is not None:
        if size_bad[i]:
            raise _invalid(
                path,
                "proposal_size",
                f"proposal {i} records {int(size[i])} members but mask_proposal assigns {int(members[i])}",
            )
        if empty[i]:
            raise _invalid(path, "proposal_size", f"proposal {i} is empty")
        raise _out_of_range(
            path,
            "proposal_views",
            i,
            int(views[i]),
            f"a view count in 1..={int(size[i])} (its member count)",
        )
    return Proposals(
        path=path,
        metadata=dict(c.metadata),
        mask_proposal=mp,
        proposal_size=size,
        proposal_views=views,
        mask_share=share,
        mask_instance=instance,
    )


def _check_share(path: str, tensor: str, share: np.ndarray) -> None:
    """Every value finite and in (0, 1] (a per-mask share)."""
    _check_finite(path, tensor, share)
    i = _first(~((share > 0) & (share <= 1)))
    if i is not None:
        raise _out_of_range(path, tensor, i, _display_float(share[i]), "a share in (0, 1]")


def _features(c: Container) -> Features:
    r = _Reader(c)
    feat_dtype = r.req_either("features", ("F16", "F32"), "N,D")
    dim = r.dim("D")
    r.req("valid", "U8", "N")
    r.opt("weight_sum", "F32", "N")
    a = r.load()
    path = c.path
    valid = a["valid"]
    n = valid.shape[0]
    if dim == 0:
        raise _shape_error(path, "features", [n, 0], "[N, D] with D >= 1")
    _check_flags(path, "valid", valid)
    features = a["features"]
    _check_finite(path, "features", features)
    _check_unit_rows(path, "features", features, feat_dtype, valid == 0)
    s = a.get("weight_sum")
    if s is not None:
        _check_finite(path, "weight_sum", s)
        i = _first(s < 0.0)
        if i is not None:
            raise _out_of_range(path, "weight_sum", i, _display_float(s[i]), "a weight >= 0")
        i = _first((s > 0.0) != (valid == 1))
        if i is not None:
            raise _invalid(
                path,
                "weight_sum",
                f"Gaussian {i} has weight {_display_float(s[i])} but valid = {int(valid[i])}",
            )
    return Features(
        path=path, metadata=dict(c.metadata), features=features, valid=valid, weight_sum=s, dim=dim
    )


def _pq(c: Container) -> Pq:
    r = _Reader(c)
    metric_expected = '"inner_product"'
    if r.meta("metric", metric_expected) != "inner_product":
        raise _meta_error(c.path, "metric", metric_expected)
    if r.meta_usize("nbits", "8") != 8:
        raise _meta_error(c.path, "nbits", "8")
    r.req("centroids", "F32", f"M,{KSUB},S")
    m, dsub = r.dim("M"), r.dim("S")
    r.req("codes", "U8", "N,M")
    r.req("norms", "F32", "N")
    r.req("valid", "U8", "N")
    a = r.load()
    path = c.path
    if m == 0 or dsub == 0:
        raise _shape_error(path, "centroids", [m, KSUB, dsub], "[M, 256, dsub] with M, dsub >= 1")
    _check_finite(path, "centroids", a["centroids"])
    valid, norms = a["valid"], a["norms"]
    _check_flags(path, "valid", valid)
    _check_finite(path, "norms", norms)
    i = _first(norms < 0.0)
    if i is not None:
        raise _out_of_range(path, "norms", i, _display_float(norms[i]), "a norm >= 0")
    i = _first((valid == 0) & (norms != 0.0))
    if i is not None:
        raise _invalid(path, "norms", f"vector {i} is invalid but has norm {_display_float(norms[i])}")
    return Pq(
        path=path,
        metadata=dict(c.metadata),
        centroids=a["centroids"],
        codes=a["codes"],
        norms=norms,
        valid=valid,
        m=m,
        dsub=dsub,
    )


def _prompts(c: Container) -> Prompts:
    r = _Reader(c)
    names = r.meta_strings("names")
    r.bind("Q", len(names), "metadata `names`")
    r.req("embeddings", "F32", "Q,D")
    dim = r.dim("D")
    r.opt("class_ids", "I32", "Q")
    a = r.load()
    path = c.path
    q = len(names)
    if dim == 0:
        raise _shape_error(path, "embeddings", [q, 0], "[Q, D] with D >= 1")
    seen: set[str] = set()
    for i, name in enumerate(names):
        if not name or name in seen:
            raise _meta_error(
                path,
                "names",
                f"unique non-empty names (entry {i} {_debug_str(name)} is empty or repeated)",
            )
        seen.add(name)
    emb = a["embeddings"]
    _check_finite(path, "embeddings", emb)
    i = _first((emb == 0.0).all(axis=1))
    if i is not None:
        raise _invalid(path, "embeddings", f"row {i} ({_debug_str(names[i])}) is all zero")
    ids = a.get("class_ids")
    if ids is not None:
        _check_class_ids(path, "class_ids", ids, "none")
    return Prompts(
        path=path, metadata=dict(c.metadata), names=names, embeddings=emb, class_ids=ids, dim=dim
    )


def _selection(c: Container) -> Selection:
    r = _Reader(c)
    prompt = r.meta("prompt", "the prompt text")
    num_gaussians = r.meta_usize("num_gaussians", "a non-negative integer")
    r.req("gaussian_ids", "U32", "S")
    r.req("scores", "F32", "S")
    a = r.load()
    path = c.path
    if not prompt:
        raise _meta_error(path, "prompt", "a non-empty prompt text")
    ids = a["gaussian_ids"].astype(np.uint64)
    range_bad = ids >= np.uint64(num_gaussians)
    order_bad = np.zeros(ids.shape, dtype=bool)
    order_bad[1:] = ids[:-1] >= ids[1:]
    i = _first(range_bad | order_bad)
    if i is not None:
        if range_bad[i]:
            raise _out_of_range(
                path,
                "gaussian_ids",
                i,
                int(ids[i]),
                f"a Gaussian id < {num_gaussians} (metadata num_gaussians)",
            )
        raise _out_of_range(path, "gaussian_ids", i, int(ids[i]), "ids in strictly increasing order")
    _check_finite(path, "scores", a["scores"])
    return Selection(
        path=path,
        metadata=dict(c.metadata),
        prompt=prompt,
        num_gaussians=num_gaussians,
        gaussian_ids=a["gaussian_ids"],
        scores=a["scores"],
    )


def _vertex_labels(c: Container) -> VertexLabels:
    r = _Reader(c)
    r.req("labels", "I32", "V")
    r.opt("confidence", "F32", "V")
    a = r.load()
    path = c.path
    labels = a["labels"]
    _check_class_ids(path, "labels", labels, "no label")
    conf = a.get("confidence")
    if conf is not None:
        _check_finite(path, "confidence", conf)
        i = _first(~((conf >= 0.0) & (conf <= 1.0)))
        if i is not None:
            raise _out_of_range(path, "confidence", i, _display_float(conf[i]), "a value in [0, 1]")
    return VertexLabels(path=path, metadata=dict(c.metadata), labels=labels, confidence=conf)


def _mesh(c: Container) -> Mesh:
    r = _Reader(c)
    r.req("vertices", "F32", "V,3", lanes=3)
    r.opt("colors", "U8", "V,3", lanes=3)
    r.opt("faces", "U32", "F,3", lanes=3)
    r.opt("labels", "U32", "V")
    r.opt("instances", "U32", "V")
    a = r.load()
    path = c.path
    vertices = a["vertices"]
    _check_finite(path, "vertices", vertices)
    faces = a.get("faces")
    if faces is not None:
        _check_ids(path, "faces", faces, vertices.shape[0], None, "the vertices")
    return Mesh(
        path=path,
        metadata=dict(c.metadata),
        vertices=vertices,
        colors=a.get("colors"),
        faces=faces,
        labels=a.get("labels"),
        instances=a.get("instances"),
    )


def _view_maps(c: Container) -> ViewMaps:
    r = _Reader(c)
    names = r.meta_strings("view_names")
    num_objects = r.meta_usize("num_objects", "a non-negative integer")
    r.bind("V", len(names), "metadata `view_names`")
    r.req("depth", "F32", "V,H,W")
    r.opt("object_ids", "U32", "V,H,W")
    height, width = r.dim("H"), r.dim("W")
    a = r.load()
    path = c.path
    for i, name in enumerate(names):
        if not name:
            raise _meta_error(path, "view_names", f"non-empty names (entry {i} is empty)")
    depth = a["depth"]
    _check_finite(path, "depth", depth)
    flat = depth.reshape(-1)
    i = _first(flat < 0.0)
    if i is not None:
        raise _out_of_range(path, "depth", i, _display_float(flat[i]), "a depth >= 0")
    ids = a.get("object_ids")
    if ids is not None:
        _check_ids(path, "object_ids", ids, num_objects, NO_OBJECT, "the objects")
    return ViewMaps(
        path=path,
        metadata=dict(c.metadata),
        view_names=names,
        num_objects=num_objects,
        depth=depth,
        object_ids=ids,
        height=height,
        width=width,
    )



@dataclasses.dataclass
class TopK(_Record):
    """``profuse.topk``: the per-pixel top-K contributors of one rendered view."""

    KIND: ClassVar[str] = "topk"
    TENSORS: ClassVar[tuple[str, ...]] = ("ids", "weights", "transmittance")

    path: str
    metadata: dict[str, str]
    #: Metadata ``num_gaussians``.
    num_gaussians: int
    #: U32 [H, W, K]: ids by decreasing weight, 4294967295 = padding.
    ids: np.ndarray
    #: F32 [H, W, K]: weights omega = T * alpha, 0 exactly on padding.
    weights: np.ndarray
    #: F32 [H, W]: final transmittance.
    transmittance: np.ndarray
    height: int
    width: int
    k: int

    def counts(self) -> dict[str, int]:
        return {
            "height": self.height,
            "width": self.width,
            "k": self.k,
            "hits": int(np.count_nonzero(self.ids != NO_GAUSSIAN)),
        }


def _topk(c: Container) -> TopK:
    r = _Reader(c)
    num_gaussians = r.meta_usize("num_gaussians", "a non-negative integer")
    r.req("ids", "U32", "H,W,K")
    r.req("weights", "F32", "H,W,K")
    r.req("transmittance", "F32", "H,W")
    height, width, k = r.dim("H"), r.dim("W"), r.dim("K")
    a = r.load()
    path = c.path
    if k == 0:
        raise _shape_error(path, "ids", [height, width, 0], "[H, W, K] with K >= 1")
    ids, weights, trans = a["ids"], a["weights"], a["transmittance"]
    _check_ids(path, "ids", ids, num_gaussians, NO_GAUSSIAN, "the Gaussians")
    _check_finite(path, "weights", weights)
    flat_w = weights.reshape(-1)
    i = _first((flat_w < 0.0) | (flat_w > 1.0))
    if i is not None:
        raise _out_of_range(path, "weights", i, _display_float(flat_w[i]), "a weight in [0, 1]")
    if height * width == 0:
        # No pixel: nothing below has an element (and K, a header value, may be too large
        # for numpy to shape a [pixels, K] view; issue 20 item 2).
        return _topk_record(c, num_gaussians, ids, weights, trans, height, width, k)
    w2 = weights.reshape(-1, k)
    pad = ids.reshape(-1, k) == NO_GAUSSIAN
    # The first defect in (pixel, slot) order: padding/weight mismatch, then ordering.
    bad_pad = pad != (w2 == 0.0)
    bad_order = np.zeros_like(bad_pad)
    bad_order[:, 1:] = w2[:, 1:] > w2[:, :-1]
    i = _first((bad_pad | bad_order).reshape(-1))
    if i is not None:
        p, s = divmod(i, k)
        w = _display_float(w2[p, s])
        if bad_pad[p, s]:
            detail = f"pixel {p} slot {s}: id {int(ids.reshape(-1, k)[p, s])} with weight {w} (padding must have weight 0, hits weight > 0)"
        else:
            detail = f"pixel {p} slot {s}: weight {w} exceeds the previous slot's {_display_float(w2[p, s - 1])}"
        raise _invalid(path, "weights", detail)
    _check_finite(path, "transmittance", trans)
    flat_t = trans.reshape(-1)
    i = _first((flat_t < 0.0) | (flat_t > 1.0))
    if i is not None:
        raise _out_of_range(path, "transmittance", i, _display_float(flat_t[i]), "a transmittance in [0, 1]")
    totals = _topk_totals(w2, flat_t)
    i = _first(totals > 1.0 + WEIGHT_SUM_TOLERANCE)
    if i is not None:
        raise _invalid(path, "weights", f"pixel {i}: weights plus transmittance sum to {totals[i]!r}, more than 1")
    return _topk_record(c, num_gaussians, ids, weights, trans, height, width, k)


def _topk_totals(w2: np.ndarray, trans: np.ndarray) -> np.ndarray:
    """Per pixel, Σ weights + T summed in f64 in slot order as the Rust reader sums
    (``cumsum`` is sequential), a bounded number of pixels at a time: no loop runs per
    slot, so the work is bounded by the data, not by K (issue 20 item 2: a Python loop
    over K = 2^31 slots hung on a 400-byte file)."""
    pixels, k = w2.shape
    totals = np.empty(pixels, dtype=np.float64)
    chunk = max(1, (1 << 22) // k)
    for start in range(0, pixels, chunk):
        x = w2[start : start + chunk].astype(np.float64)
        totals[start : start + chunk] = np.cumsum(x, axis=1)[:, -1]
    return totals + trans.astype(np.float64)


def _topk_record(
    c: Container, num_gaussians: int, ids: np.ndarray, weights: np.ndarray, trans: np.ndarray,
    height: int, width: int, k: int,
) -> TopK:
    return TopK(
        path=c.path,
        metadata=dict(c.metadata),
        num_gaussians=num_gaussians,
        ids=ids,
        weights=weights,
        transmittance=trans,
        height=height,
        width=width,
        k=k,
    )


#: Group of a mask that registers into no group (``fuse_partial.mask_group``).
NO_GROUP = _U32_MAX


@dataclasses.dataclass
class FusePartial(_Record):
    """``profuse.fuse_partial``: the exact partial sums of a ``fuse run --views a..b``
    shard (fixed-point integers in units of 2^-62, stored as (low, high) u64 words)."""

    KIND: ClassVar[str] = "fuse_partial"
    TENSORS: ClassVar[tuple[str, ...]] = (
        "views",
        "mask_group",
        "mask_proposal",
        "mask_share",
        "mask_features",
        "mask_mass",
        "w_offsets",
        "w_groups",
        "w_sums",
    )

    path: str
    metadata: dict[str, str]
    num_gaussians: int
    num_views: int
    k: int
    #: ``proposals``, ``masks`` or ``blend``.
    grouping: str
    #: ``ignore``, ``singleton``, or ``none`` for ``masks``.
    orphans: str
    num_groups: int
    pixels: int
    hits: int
    #: U32 [S]: the views summed, ascending.
    views: np.ndarray
    #: U32 [M]: group of every mask or 4294967295.
    mask_group: np.ndarray
    #: U32 [M] for grouping ``blend``, else None.
    mask_proposal: np.ndarray | None
    #: F32 [M] (each in (0, 1]) or None: the proposals' ``mask_share``.
    mask_share: np.ndarray | None
    #: F16 or F32 [M, D].
    mask_features: np.ndarray
    #: U64 [M, 2]: fixed-point masses, (low, high) words.
    mask_mass: np.ndarray
    #: U64 [N + 1]: CSR row offsets of W.
    w_offsets: np.ndarray
    #: U32 [E]: group of every entry.
    w_groups: np.ndarray
    #: U64 [E, 2]: fixed-point sums, (low, high) words.
    w_sums: np.ndarray
    dim: int

    def counts(self) -> dict[str, int]:
        return {
            "gaussians": self.num_gaussians,
            "views": self.num_views,
            "summed_views": int(self.views.shape[0]),
            "masks": int(self.mask_group.shape[0]),
            "groups": self.num_groups,
            "entries": int(self.w_groups.shape[0]),
            "feature_dim": self.dim,
        }


def fixed_point(words: Any) -> list[int]:
    """(low, high) u64 word pairs ([..., 2]) as Python integers (the u128 sums)."""
    w = np.asarray(words, dtype=np.uint64).reshape(-1, 2)
    return [int(lo) | (int(hi) << 64) for lo, hi in w]


def fixed_point_words(values: Any) -> np.ndarray:
    """Non-negative integers below 2^128 as an [n, 2] U64 array of (low, high) words."""
    out = []
    for v in values:
        v = int(v)
        if not 0 <= v < 2**128:
            raise ValueError(f"{v} is not a u128")
        out.append((v & _U64_MAX, v >> 64))
    return np.array(out, dtype="<u8").reshape(-1, 2)


def _parse_grouping(path: str, grouping: str, orphans: str) -> None:
    """``grouping`` and ``orphans`` name a known combination (Rust ``FuseGrouping::parse``)."""
    if grouping == "masks":
        if orphans != "none":
            raise _meta_error(path, "orphans", "`none` for grouping `masks`")
    elif grouping in ("proposals", "blend"):
        if orphans not in ("ignore", "singleton"):
            raise _meta_error(path, "orphans", "`ignore` or `singleton`")
    else:
        raise _meta_error(path, "grouping", "`proposals`, `masks` or `blend`")


def _fuse_partial_groups(
    path: str, grouping: str, orphans: str, num_groups: int, group: np.ndarray, proposal: np.ndarray | None
) -> None:
    """Group ids in range and the per-grouping rules (Rust ``check_groups``)."""
    g64 = group.astype(np.uint64)
    i = _first((g64 != np.uint64(NO_GROUP)) & (g64 >= np.uint64(num_groups)))
    if i is not None:
        raise _out_of_range(
            path, "mask_group", i, int(group[i]), f"a group < {num_groups} or the reserved {NO_GROUP}"
        )
    m = group.shape[0]
    own = np.arange(m, dtype=np.uint64)
    if grouping == "blend":
        if proposal is None:
            raise _missing_tensor(path, "mask_proposal", "U32 [M] for grouping `blend`")
        if num_groups != m:
            raise _meta_error(path, "num_groups", f"{m} (grouping `blend` has one group per mask)")
        none = (proposal == NO_GROUP) & (orphans == "ignore")
        expected = np.where(none, np.uint64(NO_GROUP), own)
        i = _first(g64 != expected)
        if i is not None:
            raise _invalid(
                path,
                "mask_group",
                f"mask {i}: grouping `blend` puts mask i in group i, or none when it has no "
                "proposal and orphans are ignored (`mask_proposal`)",
            )
    elif proposal is not None:
        raise _invalid(path, "mask_proposal", f"present only for grouping `blend`, not `{grouping}`")
    elif grouping == "masks" and (num_groups != m or bool(np.any(g64 != own))):
        raise _invalid(path, "mask_group", "grouping `masks` puts mask i in group i (and has G = M)")


def _fuse_partial_weights(path: str, num_groups: int, off: np.ndarray, groups: np.ndarray, sums: np.ndarray) -> None:
    """CSR rows of W: offsets, in-range groups strictly ascending per row, nonzero sums."""
    e = groups.shape[0]
    _check_offsets(path, "w_offsets", off, e)
    starts = off[:-1][off[:-1] < off[1:]].astype(np.int64)
    row_start = np.zeros(e, dtype=bool)
    row_start[starts] = True
    g = groups.astype(np.int64)
    bad = g >= num_groups
    bad[1:] |= ~row_start[1:] & (g[1:] <= g[:-1])
    j = _first(bad)
    if j is not None:
        raise _out_of_range(
            path, "w_groups", j, int(groups[j]), f"groups < {num_groups}, strictly ascending within a row"
        )
    i = _first(~sums.reshape(-1, 2).any(axis=1))
    if i is not None:
        raise _out_of_range(path, "w_sums", i, 0, "a nonzero sum")


def _fuse_partial(c: Container) -> FusePartial:
    r = _Reader(c)
    path = c.path
    integer = "a non-negative integer"
    n = r.meta_usize("num_gaussians", integer)
    num_views = r.meta_usize("num_views", integer)
    k = r.meta_usize("k", integer)
    grouping = r.meta("grouping", "`proposals`, `masks` or `blend`")
    orphans = r.meta("orphans", "`ignore`, `singleton` or `none`")
    _parse_grouping(path, grouping, orphans)
    num_groups = r.meta_usize("num_groups", integer)
    pixels = r.meta_usize("pixels", integer)
    hits = r.meta_usize("hits", integer)
    if n + 1 > _U64_MAX:
        raise _meta_error(path, "num_gaussians", "an integer below 2^64 - 1")
    r.bind("N1", n + 1, "metadata `num_gaussians` + 1")
    r.req("views", "U32", "S")
    r.req("mask_group", "U32", "M")
    has_proposal = r.opt("mask_proposal", "U32", "M")
    has_share = r.opt("mask_share", "F32", "M")
    feat_dtype = r.req_either("mask_features", ("F16", "F32"), "M,D")
    dim = r.dim("D")
    r.req("mask_mass", "U64", "M,2", lanes=2)
    r.req("w_offsets", "U64", "N1")
    r.req("w_groups", "U32", "E")
    r.req("w_sums", "U64", "E,2", lanes=2)
    a = r.load()
    m = a["mask_group"].shape[0]
    if dim == 0:
        raise _shape_error(path, "mask_features", [m, 0], "[M, D] with D >= 1")
    views = a["views"]
    v64 = views.astype(np.int64)
    bad = v64 >= num_views
    bad[1:] |= v64[:-1] >= v64[1:]
    i = _first(bad)
    if i is not None:
        raise _out_of_range(path, "views", i, int(views[i]), f"ascending unique view ids < {num_views}")
    proposal = a["mask_proposal"] if has_proposal else None
    _fuse_partial_groups(path, grouping, orphans, num_groups, a["mask_group"], proposal)
    share = a["mask_share"] if has_share else None
    if share is not None:
        if grouping == "masks":
            raise _invalid(path, "mask_share", "present only for groupings `proposals` and `blend`, not `masks`")
        _check_share(path, "mask_share", share)
    _check_finite(path, "mask_features", a["mask_features"])
    del feat_dtype  # either precision is fine; no unit-norm rule
    _fuse_partial_weights(path, num_groups, a["w_offsets"], a["w_groups"], a["w_sums"])
    return FusePartial(
        path=path,
        metadata=dict(c.metadata),
        num_gaussians=n,
        num_views=num_views,
        k=k,
        grouping=grouping,
        orphans=orphans,
        num_groups=num_groups,
        pixels=pixels,
        hits=hits,
        views=views,
        mask_group=a["mask_group"],
        mask_proposal=proposal,
        mask_share=share,
        mask_features=a["mask_features"],
        mask_mass=a["mask_mass"],
        w_offsets=a["w_offsets"],
        w_groups=a["w_groups"],
        w_sums=a["w_sums"],
        dim=dim,
    )


#: The integer counters of a ``warp_partial`` shard (metadata keys, in this order).
WARP_COUNTERS = (
    "skipped_pairs",
    "edges_tested",
    "cells_total",
    "cells_low_certainty",
    "cells_occluded",
    "cells_gated",
    "rejected_iou",
    "rejected_box_iou",
    "rejected_one_direction_only",
    "rejected_no_reverse_overlap",
)
#: The keys identifying a ``warp_partial`` shard's inputs and parameters.
WARP_INPUTS = ("input_masks", "input_matches", "input_cameras", "input_gaussians", "input_params")


@dataclasses.dataclass
class WarpPartial(_Record):
    """``profuse.warp_partial``: the accepted mask links of consecutive view pairs of a
    warp-graph run, with the shard's counters (SPEC.md 4.16)."""

    KIND: ClassVar[str] = "warp_partial"
    TENSORS: ClassVar[tuple[str, ...]] = ("pairs", "edge_offsets", "edge_masks", "edge_scores")

    path: str
    metadata: dict[str, str]
    num_views: int
    num_masks: int
    num_view_pairs: int
    first_pair: int
    #: The counters named by :data:`WARP_COUNTERS`.
    counters: dict[str, int]
    #: The values of the :data:`WARP_INPUTS` keys.
    inputs: dict[str, str]
    #: U32 [P, 2]: the view pairs (i < j), strictly ascending.
    pairs: np.ndarray
    #: U64 [P + 1]: pair p's links are ``edge_offsets[p] .. edge_offsets[p + 1]``.
    edge_offsets: np.ndarray
    #: U32 [E, 2]: global mask ids of every link.
    edge_masks: np.ndarray
    #: F64 [E, 2]: (mask IoU, box IoU) of every link.
    edge_scores: np.ndarray

    def counts(self) -> dict[str, int]:
        return {
            "views": self.num_views,
            "masks": self.num_masks,
            "view_pairs": self.num_view_pairs,
            "shard_pairs": int(self.pairs.shape[0]),
            "edges": int(self.edge_masks.shape[0]),
        }


def _warp_partial_values(path: str, v: int, m: int, a: dict[str, np.ndarray]) -> None:
    """The value rules of SPEC.md 4.16 after the first_pair check (Rust ``validate``)."""
    pairs = a["pairs"].reshape(-1, 2).astype(np.int64)
    bad = (pairs[:, 0] >= pairs[:, 1]) | (pairs[:, 1] >= v)
    if pairs.shape[0] > 1:
        earlier = (pairs[:-1, 0] < pairs[1:, 0]) | ((pairs[:-1, 0] == pairs[1:, 0]) & (pairs[:-1, 1] < pairs[1:, 1]))
        bad[1:] |= ~earlier
    k = _first(bad)
    if k is not None:
        i, j = int(pairs[k, 0]), int(pairs[k, 1])
        raise _out_of_range(path, "pairs", k, f"[{i}, {j}]", f"view pairs (i < j < {v}), strictly ascending")
    masks = a["edge_masks"].reshape(-1, 2).astype(np.int64)
    _check_offsets(path, "edge_offsets", a["edge_offsets"], masks.shape[0])
    k = _first((masks[:, 0] >= masks[:, 1]) | (masks[:, 1] >= m))
    if k is not None:
        raise _out_of_range(
            path, "edge_masks", k, f"[{masks[k, 0]}, {masks[k, 1]}]", f"global mask ids, first < second < {m}"
        )
    scores = a["edge_scores"].reshape(-1)
    _check_finite(path, "edge_scores", scores)
    k = _first(~((scores >= 0) & (scores <= 1)))
    if k is not None:
        raise _out_of_range(path, "edge_scores", k, _format_float(float(scores[k])), "a value in [0, 1]")


def _warp_partial(c: Container) -> WarpPartial:
    r = _Reader(c)
    path = c.path
    integer = "a non-negative integer"
    num_views = r.meta_usize("num_views", integer)
    num_masks = r.meta_usize("num_masks", integer)
    num_view_pairs = r.meta_usize("num_view_pairs", integer)
    first_pair = r.meta_usize("first_pair", integer)
    counters = {}
    for key in WARP_COUNTERS:
        value = _parse_usize(r.meta(key, "a decimal counter below 2^64"))
        if value is None or value > _U64_MAX:
            raise _meta_error(path, key, "a decimal counter below 2^64")
        counters[key] = value
    inputs = {key: r.meta(key, "a string identifying the input") for key in WARP_INPUTS}
    r.req("pairs", "U32", "P,2", lanes=2)
    r.bind("P1", r.dim("P") + 1, "`pairs` rows + 1")
    r.req("edge_offsets", "U64", "P1")
    r.req("edge_masks", "U32", "E,2", lanes=2)
    r.req("edge_scores", "F64", "E,2", lanes=2)
    a = r.load()
    p = a["pairs"].shape[0]
    if first_pair + p > num_view_pairs:
        raise _meta_error(
            path, "first_pair", f"first_pair + {p} (the shard's pairs) <= num_view_pairs {num_view_pairs}"
        )
    _warp_partial_values(path, num_views, num_masks, a)
    return WarpPartial(
        path=path,
        metadata=dict(c.metadata),
        num_views=num_views,
        num_masks=num_masks,
        num_view_pairs=num_view_pairs,
        first_pair=first_pair,
        counters=counters,
        inputs=inputs,
        pairs=a["pairs"],
        edge_offsets=a["edge_offsets"],
        edge_masks=a["edge_masks"],
        edge_scores=a["edge_scores"],
    )


# --------------------------------------------------------------------------------------
# semantic_index (SPEC.md 4.17)
# --------------------------------------------------------------------------------------

#: Units of ``share`` and ``min_share``: a stored q means a share of q / 255.
SHARE_SCALE = 255
#: Largest proposal count whose ``index`` is U16 (65535 stays the "none" value).
MAX_U16_PROPOSALS = 65535


def quantise_share(share: float) -> int:
    """round(255 * share) of a share clamped to [0, 1] (half away from zero, as Rust)."""
    x = min(max(float(share), 0.0), 1.0) * SHARE_SCALE
    return int(np.floor(x + 0.5))


def _index_dtype(num_proposals: int) -> str:
    return "U16" if num_proposals <= MAX_U16_PROPOSALS else "U32"


@dataclasses.dataclass
class SemanticIndex(_Record):
    """``profuse.semantic_index``: per Gaussian its dominant proposal and that proposal's
    share of its weight, plus the proposal descriptor table."""

    KIND: ClassVar[str] = "semantic_index"
    TENSORS: ClassVar[tuple[str, ...]] = ("descriptors", "index", "share")

    path: str
    metadata: dict[str, str]
    #: F16 or F32 [P, D]: unit-norm rows or all zero.
    descriptors: np.ndarray
    #: U16 (P <= 65535) or U32 [N]: dominant proposal, or the dtype's maximum (none).
    index: np.ndarray
    #: U8 [N]: share in units of 1/255, 0 where index is none; ``None`` when the file
    #: omits it (allowed only with ``min_share`` 0: the index alone, 2 bytes a Gaussian).
    share: np.ndarray | None
    #: Metadata ``min_share`` (units of 1/255).
    min_share: int
    #: Descriptor dimension D.
    dim: int

    def dominant(self) -> np.ndarray:
        """Boolean [N]: a dominant proposal (index not none, share >= min_share)."""
        none = _LABEL_NONE["U16" if self.index.dtype == np.uint16 else "U32"]
        return (self.index != none) & (self.shares() >= self.min_share)

    def shares(self) -> np.ndarray:
        """U8 [N]: the stored shares, or without them 255 where index is not none, else 0."""
        if self.share is not None:
            return self.share
        none = _LABEL_NONE["U16" if self.index.dtype == np.uint16 else "U32"]
        return np.where(self.index != none, 255, 0).astype(np.uint8)

    def counts(self) -> dict[str, int]:
        none = _LABEL_NONE["U16" if self.index.dtype == np.uint16 else "U32"]
        return {
            "gaussians": int(self.index.shape[0]),
            "proposals": int(self.descriptors.shape[0]),
            "feature_dim": self.dim,
            "indexed": int(np.count_nonzero(self.index != none)),
            "dominant": int(np.count_nonzero(self.dominant())),
        }


def _semantic_index(c: Container) -> SemanticIndex:
    r = _Reader(c)
    expected = "an integer in 0..=255 (a share in units of 1/255)"
    min_share = r.meta_usize("min_share", expected)
    if min_share > 255:
        raise _meta_error(c.path, "min_share", expected)
    desc_dtype = r.req_either("descriptors", ("F16", "F32"), "P,D")
    p, dim = r.dim("P"), r.dim("D")
    index_dtype = r.req_either("index", ("U16", "U32"), "N")
    want = _index_dtype(p)
    if index_dtype != want:
        raise _dtype_error(c.path, "index", index_dtype, f"{want} for P = {p} proposals (U16 iff P <= 65535)")
    # Required unless min_share is 0, where it cannot change which Gaussians are dominant.
    if min_share == 0:
        r.opt("share", "U8", "N")
    else:
        r.req("share", "U8", "N")
    a = r.load()
    path = c.path
    if dim == 0:
        raise _shape_error(path, "descriptors", [p, 0], "[P, D] with D >= 1")
    desc = a["descriptors"]
    _check_finite(path, "descriptors", desc)
    _check_unit_rows(path, "descriptors", desc, desc_dtype, ~np.any(desc != 0, axis=1))
    none = _LABEL_NONE[index_dtype]
    index, share = a["index"], a.get("share")
    _check_ids(path, "index", index, p, none, "the table")
    g = None if share is None else _first((index == none) & (share != 0))
    if g is not None and share is not None:
        raise _invalid(path, "share", f"Gaussian {g} has no proposal but share {int(share[g])} (expected 0)")
    return SemanticIndex(
        path=path,
        metadata=dict(c.metadata),
        descriptors=desc,
        index=index,
        share=share,
        min_share=min_share,
        dim=dim,
    )


_READERS: dict[str, Callable[[Container], _Record]] = {
    "cameras": _cameras,
    "gaussians": _gaussians,
    "masks": _masks,
    "matches": _matches,
    "sparse_matches": _sparse_matches,
    "proposals": _proposals,
    "features": _features,
    "pq": _pq,
    "prompts": _prompts,
    "selection": _selection,
    "vertex_labels": _vertex_labels,
    "mesh": _mesh,
    "view_maps": _view_maps,
    "topk": _topk,
    "fuse_partial": _fuse_partial,
    "warp_partial": _warp_partial,
    "semantic_index": _semantic_index,
}


def _read_kind(path: Any, kind: str) -> Any:
    c = open_container(path)
    _check_kind(c, kind)
    return _READERS[kind](c)


def read_cameras(path: Any) -> Cameras:
    """Reads and fully validates a ``profuse.cameras`` file."""
    return _read_kind(path, "cameras")


def read_gaussians(path: Any) -> Gaussians:
    """Reads and fully validates a ``profuse.gaussians`` file."""
    return _read_kind(path, "gaussians")


def read_masks(path: Any) -> Masks:
    """Reads and fully validates a ``profuse.masks`` file."""
    return _read_kind(path, "masks")


def read_matches(path: Any) -> Matches:
    """Reads and fully validates a ``profuse.matches`` file."""
    return _read_kind(path, "matches")


def read_sparse_matches(path: Any) -> SparseMatches:
    """Reads and fully validates a ``profuse.sparse_matches`` file."""
    return _read_kind(path, "sparse_matches")


def read_proposals(path: Any) -> Proposals:
    """Reads and fully validates a ``profuse.proposals`` file."""
    return _read_kind(path, "proposals")


def read_features(path: Any) -> Features:
    """Reads and fully validates a ``profuse.features`` file."""
    return _read_kind(path, "features")


def read_pq(path: Any) -> Pq:
    """Reads and fully validates a ``profuse.pq`` file."""
    return _read_kind(path, "pq")


def read_prompts(path: Any) -> Prompts:
    """Reads and fully validates a ``profuse.prompts`` file."""
    return _read_kind(path, "prompts")


def read_selection(path: Any) -> Selection:
    """Reads and fully validates a ``profuse.selection`` file."""
    return _read_kind(path, "selection")


def read_vertex_labels(path: Any) -> VertexLabels:
    """Reads and fully validates a ``profuse.vertex_labels`` file."""
    return _read_kind(path, "vertex_labels")


def read_mesh(path: Any) -> Mesh:
    """Reads and fully validates a ``profuse.mesh`` file."""
    return _read_kind(path, "mesh")


def read_view_maps(path: Any) -> ViewMaps:
    """Reads and fully validates a ``profuse.view_maps`` file."""
    return _read_kind(path, "view_maps")


def read_topk(path: Any) -> TopK:
    """Reads and fully validates a ``profuse.topk`` file."""
    return _read_kind(path, "topk")


def read_fuse_partial(path: Any) -> FusePartial:
    """Reads and fully validates a ``profuse.fuse_partial`` file."""
    return _read_kind(path, "fuse_partial")


def read_warp_partial(path: Any) -> WarpPartial:
    """Reads and fully validates a ``profuse.warp_partial`` file."""
    return _read_kind(path, "warp_partial")
def read_semantic_index(path: Any) -> SemanticIndex:
    """Reads and fully validates a ``profuse.semantic_index`` file."""
    return _read_kind(path, "semantic_index")


def _read_container(c: Container) -> _Record:
    """Validates a parsed container as the kind its ``format`` names."""
    found = c.metadata.get("format")
    kind = _KIND_BY_FORMAT.get(found) if found is not None else None
    if kind is None:
        raise _wrong_kind(c.path, "profuse.<kind> for a known kind", found)
    _check_kind(c, kind)
    return _READERS[kind](c)


def read_any(path: Any) -> _Record:
    """Reads and fully validates a file of whatever kind its ``__metadata__.format``
    names; returns that kind's record (``Cameras``, ``Gaussians``, ...)."""
    return _read_container(open_container(path))


# --------------------------------------------------------------------------------------
# Writers (SPEC.md 2 "Container" and "Atomic writes")
# --------------------------------------------------------------------------------------

#: Version of this module (the ``profuse-formats`` Python distribution).
__version__ = "0.1.0"
#: Default ``generator`` metadata of files this module writes.
GENERATOR = f"profuse-formats-python {__version__}"

_CONTAINER_DTYPE = {dt: name for name, dt in _NUMPY_DTYPES.items()}
_INT_RANGE = {
    "U8": (0, 2**8 - 1),
    "U16": (0, 2**16 - 1),
    "U32": (0, _U32_MAX),
    "U64": (0, _U64_MAX),
    "I8": (-(2**7), 2**7 - 1),
    "I16": (-(2**15), 2**15 - 1),
    "I32": (-(2**31), 2**31 - 1),
    "I64": (-(2**63), 2**63 - 1),
}


def _dtype_name(arr: np.ndarray) -> str | None:
    """The container dtype of a numpy array (either byte order), or None."""
    try:
        return _CONTAINER_DTYPE.get(arr.dtype.newbyteorder("<"))
    except (TypeError, ValueError):  # structured or otherwise odd dtypes
        return None


def _tensor(path: str, name: str, value: Any, allowed: tuple[str, ...]) -> np.ndarray:
    """``value`` as a little-endian C-ordered array of one of the ``allowed`` dtypes.

    An array already of an allowed dtype keeps it. Otherwise it is converted to the last
    allowed dtype (F32 for "F16 or F32", U32 for "U16 or U32") when that loses nothing
    but float precision: integers must fit the target, floats never become integers.
    """
    try:
        arr = np.asarray(value)
    except (ValueError, TypeError) as e:
        raise _shape_error(path, name, [], f"a rectangular array ({e})") from None
    found = _dtype_name(arr)
    expected = " or ".join(allowed)
    if found in allowed:
        target = found
    else:
        target = allowed[-1]
        kind = arr.dtype.kind
        to_float = target.startswith("F")
        if kind not in "biuf" or (kind == "f" and not to_float):
            raise _dtype_error(path, name, found or str(arr.dtype), expected)
        if not to_float and kind in "iu" and arr.size:
            lo, hi = _INT_RANGE[target]
            flat = arr.reshape(-1)
            i = _first((flat < lo) | (flat > hi))
            if i is not None:
                raise _out_of_range(path, name, i, int(flat[i]), f"a value that fits {target}")
    return np.ascontiguousarray(arr.astype(_NUMPY_DTYPES[target], copy=False))


def _meta_int(path: str, key: str, value: Any) -> str:
    """A non-negative integer as metadata text (decimal, no sign, no leading zeros)."""
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or int(value) < 0:
        raise _meta_error(path, key, f"a non-negative integer, got {value!r}")
    return str(int(value))


def _meta_names(path: str, key: str, values: Any) -> str:
    """A list of strings as the JSON-array metadata text the Rust writer produces."""
    if isinstance(values, str) or not all(isinstance(v, str) for v in values):
        raise _meta_error(path, key, "a list of strings")
    return json.dumps(list(values), ensure_ascii=False, separators=(",", ":"))


def _check_text(path: str, what: str, text: str) -> None:
    try:
        text.encode("utf-8")
    except UnicodeEncodeError:
        raise _header_error(path, f"{what} {text!r} is not valid UTF-8 text") from None


def encode_file(kind: str, tensors: dict[str, Any], metadata: dict[str, str]) -> bytes:
    """Serialises a file exactly as the Rust ``FileWriter`` does (SPEC.md 2), without
    validating it: compact JSON header with sorted keys, ``format`` and
    ``format_version`` added when absent, padded with spaces so that ``8 + N`` is a
    multiple of 8, tensors ordered by decreasing dtype size then name, little-endian
    C-order data. ``tensors`` values must be numpy arrays of a container dtype."""
    meta = dict(metadata)
    meta.setdefault("format", _format_name(kind))
    meta.setdefault("format_version", "1.0")
    for key, value in meta.items():
        if not isinstance(key, str) or not isinstance(value, str):
            raise _header_error("<memory>", f"metadata {key!r}: keys and values must be strings")
        _check_text("<memory>", "metadata key", key)
        _check_text("<memory>", f"metadata `{key}` value", value)
    arrays = []
    for name, value in tensors.items():
        arr = np.asarray(value)
        dtype = _dtype_name(arr)
        if dtype is None or name == "__metadata__":
            raise _dtype_error("<memory>", name, str(arr.dtype), "a container dtype (SPEC.md 2)")
        _check_text("<memory>", "tensor name", name)
        arrays.append((name, dtype, arr))
    arrays.sort(key=lambda t: (-DTYPE_SIZES[t[1]], t[0].encode("utf-8")))
    header: dict[str, Any] = {"__metadata__": meta}
    chunks = []
    offset = 0
    for name, dtype, arr in arrays:
        data = np.ascontiguousarray(arr.astype(_NUMPY_DTYPES[dtype], copy=False)).tobytes()
        header[name] = {"data_offsets": [offset, offset + len(data)], "dtype": dtype, "shape": list(arr.shape)}
        chunks.append(data)
        offset += len(data)
    text = json.dumps(header, sort_keys=True, separators=(",", ":"), ensure_ascii=False).encode("utf-8")
    text += b" " * (-(8 + len(text)) % 8)
    return struct.pack("<Q", len(text)) + text + b"".join(chunks)


def _file_type_name(mode: int) -> str:
    for test, name in (
        (stat.S_ISDIR, "directory"),
        (stat.S_ISCHR, "character device"),
        (stat.S_ISBLK, "block device"),
        (stat.S_ISFIFO, "FIFO"),
        (stat.S_ISSOCK, "socket"),
        (stat.S_ISLNK, "symbolic link"),
    ):
        if test(mode):
            return name
    return "special file"


def _check_output_file(label: str, target: str) -> None:
    """An output may only replace a regular file, or be created (the Rust writers' rule,
    ``profuse_formats::output::check_output_file``): a device, FIFO, socket or directory
    at ``target`` is an ``io`` error before anything is written. Symbolic links are
    followed, as in Rust."""
    try:
        mode = os.stat(target).st_mode
    except FileNotFoundError:
        return
    except OSError as e:
        raise _io_error(label, "cannot inspect the output path", e) from None
    if not stat.S_ISREG(mode):
        found = _file_type_name(mode)
        raise FormatError(
            "io",
            label,
            f"{label}: is a {found}; an output may only replace a regular file (or not exist)",
        )


def _write_atomically(path: Any, data: bytes, check: Callable[[str], None]) -> None:
    """Writes ``data`` to a temporary ``.profuse-tmp-*`` file next to ``path``, flushes
    it to disk, runs ``check`` on it, and renames it over ``path``; on any failure the
    temporary file is removed and ``path`` is left as it was."""
    label = _label(path)
    target = os.fspath(path)
    directory = os.path.dirname(target) or "."
    _check_output_file(label, target)
    import secrets

    flags = os.O_WRONLY | os.O_CREAT | os.O_EXCL | getattr(os, "O_BINARY", 0)
    while True:
        tmp = os.path.join(directory, ".profuse-tmp-" + secrets.token_hex(6))
        try:
            fd = os.open(tmp, flags, 0o666)
            break
        except FileExistsError:
            continue
        except OSError as e:
            raise _io_error(label, "cannot create a temporary file next to it", e) from None
    try:
        try:
            view = memoryview(data)
            while view:
                view = view[os.write(fd, view) :]
        except OSError as e:
            raise _io_error(label, "cannot write", e) from None
        try:
            os.fsync(fd)
        except OSError as e:
            raise _io_error(label, "cannot flush", e) from None
        os.close(fd)
        fd = -1
        check(tmp)
        try:
            os.replace(tmp, target)
        except OSError as e:
            raise _io_error(label, "cannot rename into place", e) from None
    except BaseException:
        if fd >= 0:
            os.close(fd)
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        raise


def write_file(
    path: Any,
    kind: str,
    tensors: dict[str, Any],
    metadata: dict[str, str] | None = None,
    *,
    generator: str | None = GENERATOR,
) -> None:
    """Writes a file of ``kind`` atomically after validating it with this module's
    reader (every rule of SPEC.md: the same errors, naming ``path``, as reading it back
    would raise). ``tensors`` maps names to numpy arrays of container dtypes;
    ``metadata`` gives the kind-specific and informational keys (``format`` and
    ``format_version`` are added). ``generator`` is stored unless ``metadata`` has one
    or it is None. Nothing is written when validation fails."""
    if kind not in KINDS:
        raise ValueError(f"unknown kind {kind!r}; one of {', '.join(KINDS)}")
    label = _label(path)
    meta = dict(metadata or {})
    if generator is not None:
        meta.setdefault("generator", generator)
    data = encode_file(kind, tensors, meta)

    def check(tmp: str) -> None:
        c = _open_container(tmp, label)
        _check_kind(c, kind)
        _READERS[kind](c)

    _write_atomically(path, data, check)


def write_record(path: Any, record: _Record) -> None:
    """Writes a record returned by a reader (``read_any`` or ``read_<kind>``) with its
    metadata and arrays unchanged: reading the result gives an equal record."""
    write_file(path, record.KIND, record.arrays(), record.metadata, generator=None)


def _finish(
    path: Any,
    kind: str,
    tensors: dict[str, Any],
    fixed: dict[str, str],
    metadata: dict[str, str] | None,
    generator: str | None,
) -> None:
    """Common tail of the per-kind writers: the kind's own keys override ``metadata``."""
    meta = dict(metadata or {})
    meta.update(fixed)
    write_file(path, kind, {k: v for k, v in tensors.items() if v is not None}, meta, generator=generator)


def _opt(path: str, name: str, value: Any, allowed: tuple[str, ...]) -> np.ndarray | None:
    return None if value is None else _tensor(path, name, value, allowed)


def write_cameras(
    path: Any,
    *,
    image_names: list[str],
    image_size: Any,
    intrinsics: Any,
    world_to_camera: Any,
    distortion: Any = None,
    metadata: dict[str, str] | None = None,
    generator: str | None = GENERATOR,
) -> None:
    """``profuse.cameras`` (SPEC.md 4.1): ``image_size`` [V, 2] (w, h), ``intrinsics``
    [V, 4] (fx, fy, cx, cy), ``world_to_camera`` [V, 3, 4] (OpenCV ``[R | t]``),
    optional ``distortion`` [V, 4] (k1, k2, p1, p2)."""
    p = _label(path)
    tensors = {
        "image_size": _tensor(p, "image_size", image_size, ("U32",)),
        "intrinsics": _tensor(p, "intrinsics", intrinsics, ("F64",)),
        "world_to_camera": _tensor(p, "world_to_camera", world_to_camera, ("F64",)),
        "distortion": _opt(p, "distortion", distortion, ("F64",)),
    }
    fixed = {"image_names": _meta_names(p, "image_names", image_names), "convention": "opencv_world_to_camera"}
    _finish(path, "cameras", tensors, fixed, metadata, generator)


def write_gaussians(
    path: Any,
    *,
    means: Any,
    log_scales: Any,
    rotations: Any,
    opacity_logits: Any,
    sh_dc: Any,
    sh_rest: Any = None,
    class_ids: Any = None,
    sh_degree: int | None = None,
    metadata: dict[str, str] | None = None,
    generator: str | None = GENERATOR,
) -> None:
    """``profuse.gaussians`` (SPEC.md 4.2), INRIA 3DGS parameters. ``sh_rest`` is
    [N, R, 3] with R = 3, 8, 15; ``sh_degree`` defaults to the degree R implies (0 when
    ``sh_rest`` is None)."""
    p = _label(path)
    rest = _opt(p, "sh_rest", sh_rest, ("F32",))
    if sh_degree is None:
        r = rest.shape[1] if rest is not None and rest.ndim == 3 else 0
        sh_degree = SH_REST_COEFFS.index(r) if r in SH_REST_COEFFS else 0
    tensors = {
        "means": _tensor(p, "means", means, ("F32",)),
        "sh_rest": rest,
        "log_scales": _tensor(p, "log_scales", log_scales, ("F32",)),
        "rotations": _tensor(p, "rotations", rotations, ("F32",)),
        "opacity_logits": _tensor(p, "opacity_logits", opacity_logits, ("F32",)),
        "sh_dc": _tensor(p, "sh_dc", sh_dc, ("F32",)),
        "class_ids": _opt(p, "class_ids", class_ids, ("I32",)),
    }
    _finish(path, "gaussians", tensors, {"sh_degree": _meta_int(p, "sh_degree", sh_degree)}, metadata, generator)


def write_masks(
    path: Any,
    *,
    view_names: list[str],
    labels: Any,
    mask_offsets: Any,
    features: Any,
    metadata: dict[str, str] | None = None,
    generator: str | None = GENERATOR,
) -> None:
    """``profuse.masks`` (SPEC.md 4.3): ``labels`` U16 or U32 [V, H, W] of view-local
    mask indices (the dtype's maximum = no mask; other integer arrays are stored as
    U32), ``mask_offsets`` [V + 1], ``features`` F16 or F32 [M, D] with unit rows
    (float64 is stored as F32)."""
    p = _label(path)
    tensors = {
        "labels": _tensor(p, "labels", labels, ("U16", "U32")),
        "mask_offsets": _tensor(p, "mask_offsets", mask_offsets, ("U32",)),
        "features": _tensor(p, "features", features, ("F16", "F32")),
    }
    _finish(path, "masks", tensors, {"view_names": _meta_names(p, "view_names", view_names)}, metadata, generator)


def write_matches(
    path: Any,
    *,
    num_views: int,
    coords: str,
    pairs: Any,
    warp: Any,
    certainty: Any,
    metadata: dict[str, str] | None = None,
    generator: str | None = GENERATOR,
) -> None:
    """``profuse.matches`` (SPEC.md 4.4): dense warps; ``coords`` is ``normalized`` or
    ``pixels``; ``warp`` [P, H, W, 2] (x before y) and ``certainty`` [P, H, W] are F16
    or F32."""
    p = _label(path)
    tensors = {
        "pairs": _tensor(p, "pairs", pairs, ("U32",)),
        "warp": _tensor(p, "warp", warp, ("F16", "F32")),
        "certainty": _tensor(p, "certainty", certainty, ("F16", "F32")),
    }
    fixed = {"num_views": _meta_int(p, "num_views", num_views), "coords": str(coords)}
    _finish(path, "matches", tensors, fixed, metadata, generator)


def write_sparse_matches(
    path: Any,
    *,
    num_views: int,
    pairs: Any,
    pair_offsets: Any,
    points_i: Any,
    points_j: Any,
    certainty: Any,
    metadata: dict[str, str] | None = None,
    generator: str | None = GENERATOR,
) -> None:
    """``profuse.sparse_matches`` (SPEC.md 4.5): pixel-pair matches in pixel
    coordinates with centres at +0.5."""
    p = _label(path)
    tensors = {
        "pairs": _tensor(p, "pairs", pairs, ("U32",)),
        "pair_offsets": _tensor(p, "pair_offsets", pair_offsets, ("U64",)),
        "points_i": _tensor(p, "points_i", points_i, ("F32",)),
        "points_j": _tensor(p, "points_j", points_j, ("F32",)),
        "certainty": _tensor(p, "certainty", certainty, ("F32",)),
    }
    _finish(path, "sparse_matches", tensors, {"num_views": _meta_int(p, "num_views", num_views)}, metadata, generator)


def write_proposals(
    path: Any,
    *,
    mask_proposal: Any,
    proposal_size: Any,
    proposal_views: Any,
    mask_share: Any = None,
    mask_instance: Any = None,
    metadata: dict[str, str] | None = None,
    generator: str | None = GENERATOR,
) -> None:
    """``profuse.proposals`` (SPEC.md 4.6): proposal id per global mask (4294967295 =
    none), members and distinct views per proposal, optionally ``mask_share`` (F32 [M],
    each in (0, 1]) and ``mask_instance`` (U32 [M]: each mask's instance, a member's
    being its proposal)."""
    p = _label(path)
    tensors = {
        "mask_proposal": _tensor(p, "mask_proposal", mask_proposal, ("U32",)),
        "proposal_size": _tensor(p, "proposal_size", proposal_size, ("U32",)),
        "proposal_views": _tensor(p, "proposal_views", proposal_views, ("U32",)),
        "mask_share": _opt(p, "mask_share", mask_share, ("F32",)),
        "mask_instance": _opt(p, "mask_instance", mask_instance, ("U32",)),
    }
    _finish(path, "proposals", tensors, {}, metadata, generator)


def write_features(
    path: Any,
    *,
    features: Any,
    valid: Any,
    weight_sum: Any = None,
    metadata: dict[str, str] | None = None,
    generator: str | None = GENERATOR,
) -> None:
    """``profuse.features`` (SPEC.md 4.7): ``features`` F16 or F32 [N, D], unit rows
    where ``valid`` (U8 [N], 0 or 1; bool arrays are accepted) and all zero elsewhere."""
    p = _label(path)
    tensors = {
        "features": _tensor(p, "features", features, ("F16", "F32")),
        "valid": _tensor(p, "valid", valid, ("U8",)),
        "weight_sum": _opt(p, "weight_sum", weight_sum, ("F32",)),
    }
    _finish(path, "features", tensors, {}, metadata, generator)


def write_pq(
    path: Any,
    *,
    centroids: Any,
    codes: Any,
    norms: Any,
    valid: Any,
    metadata: dict[str, str] | None = None,
    generator: str | None = GENERATOR,
) -> None:
    """``profuse.pq`` (SPEC.md 4.8): ``centroids`` [M, 256, dsub] (faiss's layout),
    ``codes`` U8 [N, M], ``norms`` [N], ``valid`` [N]."""
    p = _label(path)
    tensors = {
        "centroids": _tensor(p, "centroids", centroids, ("F32",)),
        "codes": _tensor(p, "codes", codes, ("U8",)),
        "norms": _tensor(p, "norms", norms, ("F32",)),
        "valid": _tensor(p, "valid", valid, ("U8",)),
    }
    _finish(path, "pq", tensors, {"metric": "inner_product", "nbits": "8"}, metadata, generator)


def write_prompts(
    path: Any,
    *,
    names: list[str],
    embeddings: Any,
    class_ids: Any = None,
    metadata: dict[str, str] | None = None,
    generator: str | None = GENERATOR,
) -> None:
    """``profuse.prompts`` (SPEC.md 4.9): unique non-empty ``names`` and their text
    embeddings [Q, D]; optional ``class_ids`` I32 [Q] (-1 = none)."""
    p = _label(path)
    tensors = {
        "embeddings": _tensor(p, "embeddings", embeddings, ("F32",)),
        "class_ids": _opt(p, "class_ids", class_ids, ("I32",)),
    }
    _finish(path, "prompts", tensors, {"names": _meta_names(p, "names", names)}, metadata, generator)


def write_selection(
    path: Any,
    *,
    prompt: str,
    num_gaussians: int,
    gaussian_ids: Any,
    scores: Any,
    metadata: dict[str, str] | None = None,
    generator: str | None = GENERATOR,
) -> None:
    """``profuse.selection`` (SPEC.md 4.10): strictly increasing ``gaussian_ids`` and
    their ``scores``."""
    p = _label(path)
    tensors = {
        "gaussian_ids": _tensor(p, "gaussian_ids", gaussian_ids, ("U32",)),
        "scores": _tensor(p, "scores", scores, ("F32",)),
    }
    fixed = {"prompt": str(prompt), "num_gaussians": _meta_int(p, "num_gaussians", num_gaussians)}
    _finish(path, "selection", tensors, fixed, metadata, generator)



def write_semantic_index(
    path: Any,
    *,
    descriptors: Any,
    index: Any,
    share: Any,
    min_share: int,
    metadata: dict[str, str] | None = None,
    generator: str | None = GENERATOR,
) -> None:
    """``profuse.semantic_index`` (SPEC.md 4.17): the proposal table ``descriptors``
    [P, D], per Gaussian its dominant proposal ``index`` [N] (stored U16 iff P <= 65535,
    the dtype's maximum = none) and ``share`` U8 [N] (units of 1/255, see
    :func:`quantise_share`; ``None`` to omit it, allowed only with ``min_share`` 0);
    ``min_share`` in the same units."""
    p = _label(path)
    desc = _tensor(p, "descriptors", descriptors, ("F16", "F32"))
    num = desc.shape[0] if desc.ndim >= 1 else 0
    tensors = {
        "descriptors": desc,
        "index": _tensor(p, "index", index, (_index_dtype(num),)),
    }
    if share is not None:
        tensors["share"] = _tensor(p, "share", share, ("U8",))
    fixed = {"min_share": _meta_int(p, "min_share", min_share)}
    _finish(path, "semantic_index", tensors, fixed, metadata, generator)


def write_vertex_labels(
    path: Any,
    *,
    labels: Any,
    confidence: Any = None,
    metadata: dict[str, str] | None = None,
    generator: str | None = GENERATOR,
) -> None:
    """``profuse.vertex_labels`` (SPEC.md 4.11): class per mesh vertex (-1 = none),
    optional ``confidence`` in [0, 1]."""
    p = _label(path)
    tensors = {
        "labels": _tensor(p, "labels", labels, ("I32",)),
        "confidence": _opt(p, "confidence", confidence, ("F32",)),
    }
    _finish(path, "vertex_labels", tensors, {}, metadata, generator)


def write_mesh(
    path: Any,
    *,
    vertices: Any,
    colors: Any = None,
    faces: Any = None,
    labels: Any = None,
    instances: Any = None,
    metadata: dict[str, str] | None = None,
    generator: str | None = GENERATOR,
) -> None:
    """``profuse.mesh`` (SPEC.md 4.12): ``vertices`` [V, 3], optional RGB ``colors``
    U8 [V, 3], ``faces`` U32 [F, 3], ``labels`` and ``instances`` U32 [V]."""
    p = _label(path)
    tensors = {
        "vertices": _tensor(p, "vertices", vertices, ("F32",)),
        "colors": _opt(p, "colors", colors, ("U8",)),
        "faces": _opt(p, "faces", faces, ("U32",)),
        "labels": _opt(p, "labels", labels, ("U32",)),
        "instances": _opt(p, "instances", instances, ("U32",)),
    }
    _finish(path, "mesh", tensors, {}, metadata, generator)


def write_view_maps(
    path: Any,
    *,
    view_names: list[str],
    num_objects: int,
    depth: Any,
    object_ids: Any = None,
    metadata: dict[str, str] | None = None,
    generator: str | None = GENERATOR,
) -> None:
    """``profuse.view_maps`` (SPEC.md 4.13): camera-space ``depth`` [V, H, W] (0 = no
    surface) and optional ``object_ids`` U32 [V, H, W] (4294967295 = none)."""
    p = _label(path)
    tensors = {
        "depth": _tensor(p, "depth", depth, ("F32",)),
        "object_ids": _opt(p, "object_ids", object_ids, ("U32",)),
    }
    fixed = {
        "view_names": _meta_names(p, "view_names", view_names),
        "num_objects": _meta_int(p, "num_objects", num_objects),
    }
    _finish(path, "view_maps", tensors, fixed, metadata, generator)


def write_topk(
    path: Any,
    *,
    num_gaussians: int,
    ids: Any,
    weights: Any,
    transmittance: Any,
    metadata: dict[str, str] | None = None,
    generator: str | None = GENERATOR,
) -> None:
    """``profuse.topk`` (SPEC.md 4.14): per-pixel top-K ``ids`` U32 [H, W, K]
    (4294967295 pads), ``weights`` [H, W, K], ``transmittance`` [H, W]."""
    p = _label(path)
    tensors = {
        "ids": _tensor(p, "ids", ids, ("U32",)),
        "weights": _tensor(p, "weights", weights, ("F32",)),
        "transmittance": _tensor(p, "transmittance", transmittance, ("F32",)),
    }
    _finish(path, "topk", tensors, {"num_gaussians": _meta_int(p, "num_gaussians", num_gaussians)}, metadata, generator)


def write_fuse_partial(
    path: Any,
    *,
    num_gaussians: int,
    num_views: int,
    k: int,
    grouping: str,
    orphans: str,
    num_groups: int,
    pixels: int,
    hits: int,
    views: Any,
    mask_group: Any,
    mask_features: Any,
    mask_mass: Any,
    w_offsets: Any,
    w_groups: Any,
    w_sums: Any,
    mask_proposal: Any = None,
    mask_share: Any = None,
    metadata: dict[str, str] | None = None,
    generator: str | None = GENERATOR,
) -> None:
    """``profuse.fuse_partial`` (SPEC.md 4.15): partial sums of a ``fuse`` view shard.
    ``mask_mass`` [M, 2] and ``w_sums`` [E, 2] are U64 (low, high) words of the
    fixed-point sums (:func:`fixed_point_words` makes them from Python integers);
    ``mask_proposal`` is given exactly for grouping ``blend``."""
    p = _label(path)
    tensors = {
        "views": _tensor(p, "views", views, ("U32",)),
        "mask_group": _tensor(p, "mask_group", mask_group, ("U32",)),
        "mask_proposal": _opt(p, "mask_proposal", mask_proposal, ("U32",)),
        "mask_share": _opt(p, "mask_share", mask_share, ("F32",)),
        "mask_features": _tensor(p, "mask_features", mask_features, ("F16", "F32")),
        "mask_mass": _tensor(p, "mask_mass", mask_mass, ("U64",)),
        "w_offsets": _tensor(p, "w_offsets", w_offsets, ("U64",)),
        "w_groups": _tensor(p, "w_groups", w_groups, ("U32",)),
        "w_sums": _tensor(p, "w_sums", w_sums, ("U64",)),
    }
    fixed = {
        "num_gaussians": _meta_int(p, "num_gaussians", num_gaussians),
        "num_views": _meta_int(p, "num_views", num_views),
        "k": _meta_int(p, "k", k),
        "grouping": str(grouping),
        "orphans": str(orphans),
        "num_groups": _meta_int(p, "num_groups", num_groups),
        "pixels": _meta_int(p, "pixels", pixels),
        "hits": _meta_int(p, "hits", hits),
    }
    _finish(path, "fuse_partial", tensors, fixed, metadata, generator)


def write_warp_partial(
    path: Any,
    *,
    num_views: int,
    num_masks: int,
    num_view_pairs: int,
    first_pair: int,
    pairs: Any,
    edge_offsets: Any,
    edge_masks: Any,
    edge_scores: Any,
    metadata: dict[str, str] | None = None,
    generator: str | None = GENERATOR,
    **fields: Any,
) -> None:
    """``profuse.warp_partial`` (SPEC.md 4.16): the evidence of a warp-graph view-pair
    shard. ``fields`` holds every counter of :data:`WARP_COUNTERS` (an integer) and every
    key of :data:`WARP_INPUTS` (a string)."""
    p = _label(path)
    tensors = {
        "pairs": _tensor(p, "pairs", pairs, ("U32",)),
        "edge_offsets": _tensor(p, "edge_offsets", edge_offsets, ("U64",)),
        "edge_masks": _tensor(p, "edge_masks", edge_masks, ("U32",)),
        "edge_scores": _tensor(p, "edge_scores", edge_scores, ("F64",)),
    }
    fixed = {
        "num_views": _meta_int(p, "num_views", num_views),
        "num_masks": _meta_int(p, "num_masks", num_masks),
        "num_view_pairs": _meta_int(p, "num_view_pairs", num_view_pairs),
        "first_pair": _meta_int(p, "first_pair", first_pair),
    }
    unknown = sorted(set(fields) - set(WARP_COUNTERS) - set(WARP_INPUTS))
    if unknown:
        raise TypeError(f"write_warp_partial() got unexpected keyword arguments {unknown}")
    for key in WARP_COUNTERS:
        fixed[key] = _meta_int(p, key, fields.get(key))
    for key in WARP_INPUTS:
        if not isinstance(fields.get(key), str):
            raise _meta_error(p, key, "a string identifying the input")
        fixed[key] = fields[key]
    _finish(path, "warp_partial", tensors, fixed, metadata, generator)


# --------------------------------------------------------------------------------------
# Inspect (SPEC.md 5)
# --------------------------------------------------------------------------------------


def inspect(path: Any) -> tuple[dict[str, Any], FormatError | None]:
    """The ``profuse inspect`` report of a file and its validation error (None if valid).

    The report is a JSON-ready dict with the keys ``counts``, ``error``, ``file``,
    ``format``, ``format_version``, ``kind``, ``metadata``, ``size_bytes``, ``tensors``
    and ``valid``; :func:`report_json` renders it exactly as the Rust tool does.
    """
    label = _label(path)
    container: Container | None = None
    error: FormatError | None = None
    counts: dict[str, int] = {}
    try:
        container = open_container(path)
        counts = _read_container(container).counts()
    except FormatError as e:
        error = e
        counts = {}
    metadata = dict(container.metadata) if container is not None else {}
    tensors = (
        {n: {"dtype": t.dtype, "shape": list(t.shape)} for n, t in container.tensors.items()}
        if container is not None
        else {}
    )
    fmt = metadata.get("format")
    report = {
        "counts": dict(sorted(counts.items())),
        "error": None if error is None else {"code": error.code, "field": error.field},
        "file": label,
        "format": fmt,
        "format_version": metadata.get("format_version"),
        "kind": _KIND_BY_FORMAT.get(fmt) if fmt is not None else None,
        "metadata": metadata,
        "size_bytes": container.file_size if container is not None else None,
        "tensors": tensors,
        "valid": error is None,
    }
    return report, error


def report_json(report: dict[str, Any]) -> str:
    """The report as ``profuse inspect`` prints it (serde_json pretty, keys sorted),
    without the trailing newline."""
    return json.dumps(report, indent=2, sort_keys=True, ensure_ascii=False)


def main(argv: list[str] | None = None) -> int:
    """Command line: ``inspect FILE``. Returns the exit code."""
    args = sys.argv[1:] if argv is None else argv
    if len(args) != 2 or args[0] != "inspect":
        print("usage: profuse_formats.py inspect FILE", file=sys.stderr)
        return 2
    report, error = inspect(args[1])
    sys.stdout.buffer.write((report_json(report) + "\n").encode("utf-8"))
    sys.stdout.flush()
    if error is not None:
        text = f"error: {error.message}\n"
        if error.cause is not None:
            text += f"  caused by: {error.cause}\n"
        sys.stderr.buffer.write(text.encode("utf-8", "replace"))
        sys.stderr.flush()
        return 1
    return 0


# ---------------------------------------------------------------------------------------
# Ground-truth JSON files (SPEC.md section 6.1): gt/scene.json and gt/mask_objects.json.
# The mirror of the Rust module ``profuse_formats::ground_truth``: the same rules, in the
# same order, with the same error codes ("io", "json", "invalid") and fields.
# ---------------------------------------------------------------------------------------

#: ``format`` of gt/scene.json and the ``version`` this reader knows.
SCENE_FORMAT = "synth.scene"
SCENE_VERSION = 1

#: The NYU40 class names (the ``nyu40`` label space); class id i is ``NYU40[i - 1]``.
NYU40 = (
    "wall", "floor", "cabinet", "bed", "chair", "sofa", "table", "door", "window",
    "bookshelf", "picture", "counter", "blinds", "desk", "shelves", "curtain", "dresser",
    "pillow", "mirror", "floormat", "clothes", "ceiling", "books", "refrigerator",
    "television", "paper", "towel", "showercurtain", "box", "whiteboard", "person",
    "nightstand", "toilet", "sink", "lamp", "bathtub", "bag", "otherstructure",
    "otherfurniture", "otherprop",
)


class GtError(Exception):
    """Why a ground-truth file could not be read: ``code`` is ``io``, ``json`` (not JSON,
    or a field missing or of the wrong type) or ``invalid`` (a value breaks a rule);
    ``field`` names the field for ``invalid``, else ``None``."""

    def __init__(self, code: str, path: str, message: str, field: str | None = None):
        super().__init__(message)
        self.code = code
        self.field = field
        self.path = path
        self.message = message

    def __repr__(self) -> str:
        return f"GtError(code={self.code!r}, field={self.field!r}, message={self.message!r})"


@dataclasses.dataclass
class SceneObject:
    """One object of gt/scene.json (index = object id of gt/views.safetensors)."""

    index: int
    name: str
    class_id: int
    class_name: str
    room: bool


@dataclasses.dataclass
class SceneTruth:
    """The parts of gt/scene.json readers outside the generator use."""

    label_space: str
    room_size: tuple[float, float, float]
    objects: list[SceneObject]

    def object_classes(self) -> list[int]:
        """The class id of every object, index = object id."""
        return [o.class_id for o in self.objects]


@dataclasses.dataclass
class MaskObjects:
    """gt/mask_objects.json: ``objects[i]`` is the object of global mask i (None: no object)."""

    objects: list[int | None]


def _gt_load(path: str | os.PathLike[str], expected: str) -> tuple[str, Any]:
    shown = os.fspath(path)
    try:
        with open(path, encoding="utf-8") as f:
            text = f.read()
    except OSError as err:
        raise GtError("io", shown, f"{shown}: cannot read: {err.strerror or err}") from err
    try:
        return shown, json.loads(text)
    except json.JSONDecodeError as err:
        raise GtError("json", shown, f"{shown}: not a valid {expected}: {err}") from err


def _gt_structure(shown: str, expected: str, ok: bool) -> None:
    if not ok:
        raise GtError("json", shown, f"{shown}: not a valid {expected}: wrong structure")


def _is_int(v: Any, lo: int = 0, hi: int = 2**64 - 1) -> bool:
    return isinstance(v, int) and not isinstance(v, bool) and lo <= v <= hi


def _is_number(v: Any) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool)


def _gt_invalid(shown: str, field: str, detail: str) -> GtError:
    return GtError("invalid", shown, f"{shown}: `{field}`: {detail}", field)


def read_scene_truth(path: str | os.PathLike[str]) -> SceneTruth:
    """Reads and validates gt/scene.json (rules of SPEC.md section 6.1)."""
    expected = "gt/scene.json"
    shown, j = _gt_load(path, expected)
    room = j.get("room") if isinstance(j, dict) else None
    size = room.get("size") if isinstance(room, dict) else None
    objects = j.get("objects") if isinstance(j, dict) else None
    _gt_structure(
        shown,
        expected,
        isinstance(j, dict)
        and isinstance(j.get("format"), str)
        and _is_int(j.get("version"), 0, 2**32 - 1)
        and isinstance(j.get("label_space"), str)
        and isinstance(size, list)
        and len(size) == 3
        and all(_is_number(v) for v in size)
        and isinstance(objects, list),
    )
    parsed = []
    for o in objects:
        _gt_structure(
            shown,
            expected,
            isinstance(o, dict)
            and _is_int(o.get("index"), 0, 2**32 - 1)
            and isinstance(o.get("name"), str)
            and _is_int(o.get("class_id"), 0, 2**32 - 1)
            and isinstance(o.get("class_name"), str)
            and isinstance(o.get("room"), bool),
        )
        parsed.append(SceneObject(o["index"], o["name"], o["class_id"], o["class_name"], o["room"]))
    if j["format"] != SCENE_FORMAT:
        raise _gt_invalid(shown, "format", f"{j['format']!r}, expected {SCENE_FORMAT!r}")
    if j["version"] != SCENE_VERSION:
        raise _gt_invalid(shown, "version", f"{j['version']}, expected {SCENE_VERSION}")
    if not all(math.isfinite(v) and v > 0 for v in size):
        raise _gt_invalid(shown, "room.size", f"{size}, expected three finite lengths > 0")
    names: set[str] = set()
    for i, o in enumerate(parsed):
        if o.index != i:
            raise _gt_invalid(shown, f"objects[{i}].index", f"{o.index}, expected {i}")
        if not o.name or o.name in names:
            raise _gt_invalid(shown, f"objects[{i}].name", f"{o.name!r}, expected a unique name")
        names.add(o.name)
        if j["label_space"] == "nyu40":
            if not 1 <= o.class_id <= len(NYU40):
                raise _gt_invalid(
                    shown, f"objects[{i}].class_id", f"{o.class_id}, expected a NYU40 id in 1..=40"
                )
            if o.class_name != NYU40[o.class_id - 1]:
                raise _gt_invalid(
                    shown,
                    f"objects[{i}].class_name",
                    f"{o.class_name!r}, expected {NYU40[o.class_id - 1]!r}",
                )
    return SceneTruth(j["label_space"], (size[0], size[1], size[2]), parsed)


def read_mask_objects(path: str | os.PathLike[str]) -> MaskObjects:
    """Reads and validates gt/mask_objects.json (rules of SPEC.md section 6.1)."""
    expected = "gt/mask_objects.json"
    shown, j = _gt_load(path, expected)
    masks = j.get("masks") if isinstance(j, dict) else None
    _gt_structure(
        shown,
        expected,
        isinstance(j, dict) and _is_int(j.get("num_masks")) and isinstance(masks, list),
    )
    for m in masks:
        _gt_structure(
            shown,
            expected,
            isinstance(m, dict)
            and _is_int(m.get("id"))
            and (m.get("object") is None or _is_int(m["object"], 0, 2**32 - 1)),
        )
    n = j["num_masks"]
    if len(masks) != n:
        raise _gt_invalid(shown, "masks", f"{len(masks)} entries, expected num_masks = {n}")
    objects: list[int | None] = [None] * n
    seen = [False] * n
    for k, m in enumerate(masks):
        if m["id"] >= n or seen[m["id"]]:
            raise _gt_invalid(shown, f"masks[{k}].id", f"{m['id']}, expected each of 0..{n} once")
        if m.get("object") == 2**32 - 1:
            raise _gt_invalid(shown, f"masks[{k}].object", "4294967295 is reserved")
        seen[m["id"]] = True
        objects[m["id"]] = m.get("object")
    return MaskObjects(objects)


__all__ += [
    "GtError",
    "SceneObject",
    "SceneTruth",
    "MaskObjects",
    "read_scene_truth",
    "read_mask_objects",
]


if __name__ == "__main__":
    sys.exit(main())
