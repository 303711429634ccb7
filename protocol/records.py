"""Records: frozen dataclasses declared with CBOR keys and limits, and the bounded CBOR scan.

The machinery under every message of :mod:`protocol.messages` (and ``SlotInfo``):

* :func:`wire` declares a field: its small integer CBOR key and the limits checked on it
  (range, length, allowed lengths, items, finiteness);
* :class:`Record` checks and normalises every field on construction (bytes-likes to
  bytes, lists to tuples, ints to enums, maps to nested records; ``ValueError`` naming
  the field on a bad value), encodes itself as a canonical CBOR map (``None`` fields
  omitted) and is rebuilt from a decoded map (unknown keys ignored, a missing
  required key named);
* :func:`scan_cbor` walks an untrusted body before cbor2 sees a byte and rejects tags,
  indefinite lengths, undefined/simple values, duplicate or non-int/text map keys,
  trailing bytes, lengths past the end and nesting deeper than ``max_depth``, so cbor2
  never allocates more than the frame holds.

What the fields mean, and which message has which, is :mod:`protocol.messages`; a new
field type or limit is added here. docs/protocol.md section 2 is the specification.
"""

from __future__ import annotations

import dataclasses
import math
import types
import typing
from dataclasses import dataclass
from enum import IntEnum
from typing import Any, ClassVar, Union

from protocol.errors import MalformedMessage

__all__ = ["MAX_DEPTH", "U8", "U16", "U32", "U64", "Record", "scan_cbor", "wire"]

MAX_DEPTH = 8
"""Default nesting limit for CBOR bodies (the deepest message needs 3)."""

U8, U16, U32, U64 = (1 << 8) - 1, (1 << 16) - 1, (1 << 32) - 1, (1 << 64) - 1
"""Largest unsigned integers of 8, 16, 32 and 64 bits (field limits)."""


# --------------------------------------------------------------------------- fields


@dataclass(frozen=True)
class _Limits:
    ge: float | None = None
    le: float | None = None
    min_len: int | None = None
    max_len: int | None = None
    lengths: tuple[int, ...] | None = None
    max_items: int | None = None
    finite: bool = True


_NO_DEFAULT = dataclasses.MISSING


def wire(
    key: int,
    *,
    default: Any = _NO_DEFAULT,
    ge: float | None = None,
    le: float | None = None,
    min_len: int | None = None,
    max_len: int | None = None,
    lengths: tuple[int, ...] | None = None,
    max_items: int | None = None,
    finite: bool = True,
    repr: bool = True,
) -> Any:
    """Declare a message field: its CBOR key and the limits checked on it.

    Parameters
    ----------
    key : int
        CBOR map key, 0..255, unique within the message.
    default : optional
        Makes the key optional on the wire; ``None`` values are not encoded.
    ge, le : number, optional
        Inclusive range for ints and floats (also each element of a tuple).
    min_len, max_len : int, optional
        Length range of bytes (bytes) and str (UTF-8 bytes) fields, or of
        each bytes/str value in a dict.
    lengths : tuple of int, optional
        The only lengths allowed for a bytes field (e.g. ``(0, 32)``).
    max_items : int, optional
        Most elements of a tuple or entries of a dict.
    finite : bool
        Floats must be finite (default).
    repr : bool
        Include the field in ``repr`` (off for bulk payloads).
    """
    if not 0 <= key <= U8:
        raise ValueError(f"wire key={key} must be in [0, 255]")
    limits = _Limits(ge, le, min_len, max_len, lengths, max_items, finite)
    metadata = {"key": key, "limits": limits}
    if default is _NO_DEFAULT:
        return dataclasses.field(metadata=metadata, repr=repr)
    return dataclasses.field(default=default, metadata=metadata, repr=repr)


@dataclass(frozen=True)
class _FieldSpec:
    name: str
    key: int
    tp: Any
    required: bool
    default: Any
    limits: _Limits


Scalar = Union[int, float, str, bytes, bool]  # noqa: UP007 (a runtime alias)
Detail = dict[str, Scalar]
"""Type of ERROR/NOTICE ``detail``: text keys to scalar values."""

_SCALAR_TYPES = (bool, int, float, str, bytes)


def _describe(value: Any) -> str:
    text = repr(value)
    if len(text) > 40:
        text = text[:37] + "..."
    return f"{type(value).__name__} {text}"


def _check_length(size: int, lim: _Limits, what: str) -> None:
    if lim.lengths is not None and size not in lim.lengths:
        raise ValueError(f"{what} must be {' or '.join(map(str, lim.lengths))} bytes, got {size}")
    if lim.min_len is not None and size < lim.min_len:
        raise ValueError(f"{what} must be at least {lim.min_len} bytes, got {size}")
    if lim.max_len is not None and size > lim.max_len:
        raise ValueError(f"{what} must be at most {lim.max_len} bytes, got {size}")


def _check_range(value: float, lim: _Limits, what: str) -> None:
    if lim.ge is not None and value < lim.ge:
        raise ValueError(f"{what}={value} is below the minimum {lim.ge}")
    if lim.le is not None and value > lim.le:
        raise ValueError(f"{what}={value} is above the maximum {lim.le}")


def _coerce(value: Any, tp: Any, lim: _Limits, what: str) -> Any:
    """Check ``value`` against type ``tp`` and limits; return it normalised.

    Normalises bytearray/memoryview -> bytes, int -> float for float fields,
    int -> IntEnum, list -> tuple, dict -> Record. Raises ValueError naming
    ``what`` on any mismatch.
    """
    origin = typing.get_origin(tp)
    if origin is Union or origin is types.UnionType:
        args = typing.get_args(tp)
        if value is None:
            if type(None) in args:
                return None
            raise ValueError(f"{what} must not be null")
        members = [a for a in args if a is not type(None)]
        if len(members) == 1:
            return _coerce(value, members[0], lim, what)
        # A union of scalars (Detail values): the value's own type must be listed.
        for member in members:
            if type(value) is member or (member is bytes and isinstance(value, bytes)):
                return _coerce(value, member, lim, what)
        names = ", ".join(m.__name__ for m in members)
        raise ValueError(f"{what} must be one of {names}, got {_describe(value)}")
    if tp is bool:
        if not isinstance(value, bool):
            raise ValueError(f"{what} must be a bool, got {_describe(value)}")
        return value
    if isinstance(tp, type) and issubclass(tp, IntEnum):
        if not isinstance(value, int) or isinstance(value, bool):
            raise ValueError(f"{what} must be an int ({tp.__name__}), got {_describe(value)}")
        try:
            return tp(value)
        except ValueError:
            allowed = ", ".join(f"{m.name}={m.value}" for m in tp)
            raise ValueError(f"{what}={value} is not a {tp.__name__} ({allowed})") from None
    if tp is int:
        if not isinstance(value, int) or isinstance(value, bool):
            raise ValueError(f"{what} must be an int, got {_describe(value)}")
        _check_range(value, lim, what)
        return int(value)
    if tp is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ValueError(f"{what} must be a number, got {_describe(value)}")
        value = float(value)
        if lim.finite and not math.isfinite(value):
            raise ValueError(f"{what}={value} must be finite")
        _check_range(value, lim, what)
        return value
    if tp is str:
        if not isinstance(value, str):
            raise ValueError(f"{what} must be a text string, got {_describe(value)}")
        try:
            size = len(value.encode("utf-8"))
        except UnicodeEncodeError:
            raise ValueError(f"{what} is not valid UTF-8 (lone surrogate)") from None
        _check_length(size, lim, f"{what} (UTF-8)")
        return value
    if tp is bytes:
        if not isinstance(value, (bytes, bytearray, memoryview)):
            raise ValueError(f"{what} must be a byte string, got {_describe(value)}")
        value = bytes(value)
        _check_length(len(value), lim, what)
        return value
    if origin is tuple:
        (item_tp, _ellipsis) = typing.get_args(tp)
        if not isinstance(value, (list, tuple)):
            raise ValueError(f"{what} must be an array, got {_describe(value)}")
        if lim.max_items is not None and len(value) > lim.max_items:
            raise ValueError(f"{what} has {len(value)} items, at most {lim.max_items} allowed")
        return tuple(_coerce(v, item_tp, lim, f"{what}[{i}]") for i, v in enumerate(value))
    if origin is dict:
        _key_tp, value_tp = typing.get_args(tp)
        if not isinstance(value, dict):
            raise ValueError(f"{what} must be a map, got {_describe(value)}")
        if lim.max_items is not None and len(value) > lim.max_items:
            raise ValueError(f"{what} has {len(value)} entries, at most {lim.max_items} allowed")
        out = {}
        for k, v in value.items():
            if not isinstance(k, str) or len(k.encode("utf-8", "replace")) > 32:
                raise ValueError(f"{what} keys must be text of at most 32 bytes, got {k!r:.40}")
            out[k] = _coerce(v, value_tp, lim, f"{what}[{k!r}]")
        return out
    if isinstance(tp, type) and issubclass(tp, Record):
        if isinstance(value, tp):
            return value
        if isinstance(value, dict):
            return tp._from_map(value, what)
        raise ValueError(f"{what} must be a {tp.__name__} map, got {_describe(value)}")
    raise TypeError(f"{what}: unsupported field type {tp!r}")  # a bug in a declaration


def _plain(value: Any) -> Any:
    """Turn a field value into what cbor2 encodes (Records -> int-keyed maps)."""
    if isinstance(value, Record):
        return value._to_map()
    if isinstance(value, bool) or value is None:
        return value
    if isinstance(value, IntEnum):
        return int(value)
    if isinstance(value, tuple):
        return [_plain(v) for v in value]
    if isinstance(value, dict):
        return {k: _plain(v) for k, v in value.items()}
    return value


# --------------------------------------------------------------------------- CBOR scan


def scan_cbor(body: bytes, *, max_depth: int = MAX_DEPTH, where: str = "decode") -> None:
    """Check that ``body`` is exactly one CBOR item this protocol accepts.

    Accepted: unsigned/negative ints, byte and text strings, arrays and maps of
    definite length, false/true/null and half/single/double floats. Rejected:
    tags, indefinite lengths, undefined and other simple values, reserved
    additional-info values, map keys other than ints and text strings, duplicate
    keys, lengths running past the end of ``body``, nesting deeper than
    ``max_depth``, and trailing bytes.

    Parameters
    ----------
    body : bytes
        The CBOR body of one frame.
    max_depth : int
        Most nested arrays/maps (the top-level map counts as 1).
    where : str
        Operation named at the start of error messages.

    Raises
    ------
    MalformedMessage
        One line naming the offset and the problem.
    """
    n = len(body)
    pos = 0
    # Open containers: [items left, is_map, keys seen (maps only)].
    stack: list[list[Any]] = []
    root_left = 1
    while True:
        if pos >= n:
            raise MalformedMessage(f"{where}: CBOR truncated at offset {pos} of {n}")
        start = pos
        ib = body[pos]
        major, info = ib >> 5, ib & 0x1F
        pos += 1
        if info < 24:
            arg = info
        elif info <= 27:
            size = 1 << (info - 24)
            if pos + size > n:
                raise MalformedMessage(f"{where}: CBOR truncated at offset {pos} of {n}")
            arg = int.from_bytes(body[pos : pos + size], "big")
            pos += size
        elif info == 31:
            raise MalformedMessage(f"{where}: CBOR indefinite length at offset {start} not allowed")
        else:
            raise MalformedMessage(f"{where}: CBOR reserved value 0x{ib:02x} at offset {start}")
        # Is this item a map key?
        if stack:
            parent = stack[-1]
            if parent[1] and parent[0] % 2 == 0:
                _check_map_key(body, pos, start, major, arg, parent[2], where)
            parent[0] -= 1
        else:
            root_left -= 1
        if major in (2, 3):
            if arg > n - pos:
                raise MalformedMessage(
                    f"{where}: CBOR string of {arg} bytes at offset {start} runs past "
                    f"the end of {n}"
                )
            pos += arg
        elif major in (4, 5):
            count = arg * 2 if major == 5 else arg
            if count > n - pos:
                raise MalformedMessage(
                    f"{where}: CBOR container of {arg} items at offset {start} cannot fit the "
                    f"{n - pos} bytes left"
                )
            if count:
                if len(stack) + 1 > max_depth:
                    raise MalformedMessage(
                        f"{where}: CBOR nesting deeper than max_depth={max_depth} at offset {start}"
                    )
                stack.append([count, major == 5, set()])
        elif major == 6:
            raise MalformedMessage(f"{where}: CBOR tag {arg} at offset {start} not allowed")
        elif major == 7 and info not in (20, 21, 22, 25, 26, 27):
            raise MalformedMessage(
                f"{where}: CBOR simple value 0x{ib:02x} at offset {start} not allowed "
                "(only false, true, null and floats)"
            )
        while stack and stack[-1][0] == 0:
            stack.pop()
        if not stack and root_left == 0:
            break
    if pos != n:
        raise MalformedMessage(f"{where}: {n - pos} trailing byte(s) after the CBOR item")


def _check_map_key(body: bytes, pos: int, start: int, major: int, arg: int, seen: set,
                   where: str) -> None:
    """The item at ``start`` (its argument read up to ``pos``) is a map's key: an int or a
    text string within ``body``, not one of the map's keys ``seen`` before (added)."""
    n = len(body)
    if major in (0, 1):
        key_id: Any = (major, arg)
    elif major == 3:
        if arg > n - pos:
            raise MalformedMessage(
                f"{where}: CBOR text of {arg} bytes at offset {start} runs past "
                f"the end of {n}"
            )
        key_id = (3, body[pos : pos + arg])
    else:
        raise MalformedMessage(
            f"{where}: CBOR map key at offset {start} is major type {major} "
            "(only ints and text strings allowed)"
        )
    if key_id in seen:
        raise MalformedMessage(f"{where}: CBOR duplicate map key at offset {start}")
    seen.add(key_id)


# --------------------------------------------------------------------------- Record


class Record:
    """Base of frozen dataclasses encoded as CBOR maps with small integer keys.

    Subclasses declare fields with :func:`wire`. Construction checks every
    field (``ValueError`` on a bad value: a bug in the caller) and normalises
    it (bytes-likes to bytes, lists to tuples, ints to enums).
    """

    _specs_cache: ClassVar[dict[type, tuple[_FieldSpec, ...]]] = {}

    @classmethod
    def _specs(cls) -> tuple[_FieldSpec, ...]:
        specs = Record._specs_cache.get(cls)
        if specs is None:
            hints = typing.get_type_hints(cls)
            out = []
            keys: set[int] = set()
            for f in dataclasses.fields(cls):  # type: ignore[arg-type]
                if "key" not in f.metadata:
                    raise TypeError(f"{cls.__name__}.{f.name} is not declared with wire()")
                key = f.metadata["key"]
                if key in keys:
                    raise TypeError(f"{cls.__name__}: CBOR key {key} used twice")
                keys.add(key)
                required = f.default is dataclasses.MISSING
                out.append(
                    _FieldSpec(
                        f.name, key, hints[f.name], required, f.default, f.metadata["limits"]
                    )
                )
            specs = tuple(out)
            Record._specs_cache[cls] = specs
        return specs

    def __post_init__(self) -> None:
        name = type(self).__name__
        for spec in self._specs():
            value = getattr(self, spec.name)
            if value is None and not spec.required and spec.default is None:
                continue
            checked = _coerce(value, spec.tp, spec.limits, f"{name}.{spec.name} (key {spec.key})")
            if checked is not value:
                object.__setattr__(self, spec.name, checked)
        self._check()

    def _check(self) -> None:
        """Cross-field checks of a subclass (raise ValueError)."""

    def _to_map(self) -> dict[int, Any]:
        out = {}
        for spec in self._specs():
            value = getattr(self, spec.name)
            if value is not None:
                out[spec.key] = _plain(value)
        return out

    @classmethod
    def _from_map(cls, obj: dict[Any, Any], where: str) -> Any:
        """Build from a decoded CBOR map; raise ValueError naming the problem."""
        kwargs = {}
        for spec in cls._specs():
            if spec.key in obj:
                kwargs[spec.name] = obj[spec.key]
            elif spec.required:
                raise ValueError(f"{where}: missing required key {spec.key} ({spec.name})")
        # Construction runs the checks with the class-qualified field names.
        return cls(**kwargs)
