"""CDR codecs generated once per message type, for little-endian payloads on a little-endian host.

rosbags generates a serializer and a deserializer per type too, but they call one another per
nested type through the typestore, size a message in a first pass and pack one field per call.
Here a type's nested messages are inlined, consecutive scalars whose offsets are known when the
code is generated are read or written by one ``struct`` call, and the payload is assembled from
its pieces in one join (no sizing pass). Arrays of numbers decode as read-only numpy views into
the payload, as rosbags' do, and the objects are the typestore's classes.

Alignment follows CDR as rosbags writes it: every number at a multiple of its size from the
start of the body (after the 4-byte encapsulation header), string and sequence lengths at a
multiple of 4, the elements of an empty sequence not aligned. ``tests/unit/test_msgs_codec.py``
checks every registered type against rosbags, byte for byte and field for field.
"""

from __future__ import annotations

import struct
from collections.abc import Callable
from typing import Any

import numpy as np
from rosbags.serde.utils import ndtype
from rosbags.typesys.base import Nodetype

FORMATS = {"bool": "?", "byte": "b", "char": "B", "int8": "b", "uint8": "B", "int16": "h", "uint16": "H",
           "int32": "i", "uint32": "I", "int64": "q", "uint64": "Q", "float32": "f", "float64": "d"}
HEADER_LE = b"\x00\x01\x00\x00"  # CDR encapsulation: plain CDR, little endian, no options
ZEROS = tuple(bytes(n) for n in range(8))
_U32 = struct.Struct("<I")


class UnsupportedTypeError(Exception):
    """A field kind the generator does not handle (e.g. wstring, float128): rosbags' codec is used."""


def _size(base: str) -> int:
    return struct.calcsize(FORMATS[base])


def _after(g: int, n: int) -> int:
    """The alignment known of ``pos + n`` when ``pos`` is a multiple of ``g``."""
    return g if n == 0 else min(g, n & -n)


def _string_de(buf: bytes, pos: int) -> tuple[str, int]:
    pos = (pos + 3) & -4
    (length,) = _U32.unpack_from(buf, pos)
    end = pos + 4 + length
    if length < 1 or end > len(buf) or buf[end - 1] != 0:
        raise ValueError(f"string of {length} bytes at {pos} does not fit a {len(buf)}-byte payload")
    return str(buf[pos + 4:end - 1], "utf-8"), end


def _string_se(text: str, out: list, pos: int) -> int:
    pad = -pos & 3
    raw = text.encode()
    out += (ZEROS[pad], _U32.pack(len(raw) + 1), raw, b"\x00")
    return pos + pad + 5 + len(raw)


def _array(value: Any, dtype: np.dtype) -> np.ndarray:
    """``value`` as a contiguous array of ``dtype``; a conversion that could change values is refused."""
    if type(value) is np.ndarray and value.dtype == dtype and value.flags.c_contiguous:
        return value
    if isinstance(value, (bytes, bytearray, memoryview)) and dtype.itemsize == 1:
        return np.frombuffer(value, dtype)
    arr = np.asarray(value)
    if arr.dtype != dtype and not np.can_cast(arr.dtype, dtype, "same_kind"):
        raise TypeError(f"array of {arr.dtype} where the field holds {dtype}")
    return np.ascontiguousarray(arr, dtype)


class _Source:
    """Lines of generated code and the objects they refer to by name."""

    def __init__(self, store: Any) -> None:
        self.store = store
        self.ns: dict[str, Any] = {"np": np, "ZEROS": ZEROS, "U32": _U32, "string_de": _string_de,
                                   "string_se": _string_se, "array": _array}
        self.funcs: list[list[str]] = []
        self.helpers: dict[tuple[str, str], str] = {}
        self._n = 0

    def fresh(self, prefix: str) -> str:
        self._n += 1
        return f"{prefix}{self._n}"

    def ref(self, prefix: str, obj: Any) -> str:
        for name, value in self.ns.items():
            if value is obj and name.startswith(prefix):
                return name
        name = self.fresh(prefix)
        self.ns[name] = obj
        return name

    def fields(self, msgtype: str) -> list[tuple[str, tuple]]:
        return self.store.get_msgdef(msgtype).fields

    def cls(self, msgtype: str) -> str:
        return self.ref("C", self.store.types[msgtype])

    def dtype(self, base: str) -> str:
        return self.ref("D", np.dtype(getattr(np, ndtype(base))))

    def compile(self, entry: str) -> Callable:
        exec("\n".join(line for func in self.funcs for line in func), self.ns)  # noqa: S102
        return self.ns[entry]


class _Body:
    """One generated function: its lines, and what is known of ``pos`` where the code stands.

    ``g``: ``pos`` is a multiple of ``g``; ``run``: scalars at static offsets from ``pos`` not yet
    read or written, flushed as one struct call before anything whose offset depends on data."""

    def __init__(self, src: _Source, header: str, g: int) -> None:
        self.src, self.g, self.indent = src, g, "    "
        self.lines = [header]
        self.run: list[tuple[str, str, int]] = []  # (expression or target, format, offset)
        self.off = 0

    def emit(self, line: str) -> None:
        self.lines.append(self.indent + line)

    def scalar(self, expr: str, base: str) -> None:
        size = _size(base)
        if size > self.g:
            self.align(size)
        self.off = (self.off + size - 1) & -size
        self.run.append((expr, FORMATS[base], self.off))
        self.off += size

    def align(self, size: int) -> None:
        """Flush, then bring ``pos`` to a multiple of ``size`` (padding, when writing)."""
        self.flush()
        if size > self.g:
            self.align_code(size, "")
            self.g = size

    def align_code(self, size: int, indent: str) -> None:
        raise NotImplementedError

    def flush(self) -> None:
        if not self.run:
            return
        fmt, at = "<", 0
        for _, code, off in self.run:
            fmt += "x" * (off - at) + code
            at = off + struct.calcsize(code)
        packer = self.src.ref("S", struct.Struct(fmt))
        self.flush_run(packer, [expr for expr, _, _ in self.run])
        self.emit(f"pos += {self.off}")
        self.g = _after(self.g, self.off)
        self.run, self.off = [], 0

    def flush_run(self, packer: str, exprs: list[str]) -> None:
        raise NotImplementedError


class _Reader(_Body):
    def align_code(self, size: int, indent: str) -> None:
        # pos counts from the start of the payload, alignment from the body 4 bytes further
        self.emit(f"{indent}pos = (pos + {size - 1}) & -{size}" if size <= 4 else
                  f"{indent}pos = ((pos + {size - 5}) & -{size}) + 4")

    def flush_run(self, packer: str, exprs: list[str]) -> None:
        self.emit(f"{', '.join(exprs)}, = {packer}.unpack_from(buf, pos)")

    def message(self, msgtype: str) -> str:
        """Code reading ``msgtype`` at ``pos``; returns the expression of the object."""
        values = [self.field(desc) for _, desc in self.src.fields(msgtype)]
        return f"{self.src.cls(msgtype)}({', '.join(values)})"

    def field(self, desc: tuple) -> str:
        kind, arg = desc
        if kind == Nodetype.NAME:
            return self.message(arg)
        var = self.src.fresh("v")
        if kind == Nodetype.BASE:
            if arg[0] == "string":
                self.flush()
                self.emit(f"{var}, pos = string_de(buf, pos)")
                self.g = 1
            elif arg[0] in FORMATS:
                self.scalar(var, arg[0])
            else:
                raise UnsupportedTypeError(arg[0])
            return var
        sub, length = arg
        if kind == Nodetype.ARRAY:
            count = str(length)
        elif kind == Nodetype.SEQUENCE:
            count = self.src.fresh("n")
            self.scalar(count, "uint32")
            self.flush()
        else:
            raise UnsupportedTypeError(str(kind))
        if sub[0] == Nodetype.BASE and sub[1][0] in FORMATS:
            size = _size(sub[1][0])
            if kind == Nodetype.ARRAY:
                self.align(size)
            elif size > self.g:
                self.emit(f"if {count}:")
                self.align_code(size, "    ")
            self.emit(f"{var} = np.frombuffer(buf, {self.src.dtype(sub[1][0])}, {count}, pos)")
            self.emit(f"pos += {count} * {size}")
            self.g = _after(self.g, length * size) if kind == Nodetype.ARRAY else min(self.g, size)
            return var
        item = self.item_reader(sub)
        self.emit(f"{var} = []")
        if kind == Nodetype.SEQUENCE:  # often empty: then no loop is set up
            self.emit(f"if {count}:")
            self.emit(f"    if {count} > len(buf) - pos:")
            self.emit(f"        raise ValueError(f'sequence of {{{count}}} items beyond the payload')")
        pad = "    " if kind == Nodetype.SEQUENCE else ""
        self.emit(f"{pad}for _ in range({count}):")
        self.emit(f"{pad}    item, pos = {item}(buf, pos)")
        self.emit(f"{pad}    {var}.append(item)")
        self.g = 1
        return var

    def item_reader(self, sub: tuple) -> str:
        if sub[0] == Nodetype.BASE:
            if sub[1][0] != "string":
                raise UnsupportedTypeError(sub[1][0])
            return "string_de"
        if sub[0] != Nodetype.NAME:
            raise UnsupportedTypeError(str(sub[0]))
        key = ("de", sub[1])
        if key not in self.src.helpers:
            name = self.src.helpers[key] = self.src.fresh("de_")
            body = _Reader(self.src, f"def {name}(buf, pos):", 1)
            obj = body.message(sub[1])
            body.flush()
            body.emit(f"return {obj}, pos")
            self.src.funcs.append(body.lines)
        return self.src.helpers[key]


class _Writer(_Body):
    def flush_run(self, packer: str, exprs: list[str]) -> None:
        self.emit(f"out.append({packer}.pack({', '.join(exprs)}))")

    def align_code(self, size: int, indent: str) -> None:
        self.emit(f"{indent}pad = -pos & {size - 1}")
        self.emit(f"{indent}out.append(ZEROS[pad])")
        self.emit(f"{indent}pos += pad")

    def message(self, msgtype: str, obj: str) -> None:
        for name, desc in self.src.fields(msgtype):
            self.field(f"{obj}.{name}", desc)

    def field(self, value: str, desc: tuple) -> None:
        kind, arg = desc
        if kind == Nodetype.NAME:
            var = self.src.fresh("m")
            self.emit(f"{var} = {value}")
            self.message(arg, var)
            return
        if kind == Nodetype.BASE:
            if arg[0] == "string":
                self.flush()
                self.emit(f"pos = string_se({value}, out, pos)")
                self.g = 1
            elif arg[0] in FORMATS:
                self.scalar(value, arg[0])
            else:
                raise UnsupportedTypeError(arg[0])
            return
        sub, length = arg
        if kind not in (Nodetype.ARRAY, Nodetype.SEQUENCE):
            raise UnsupportedTypeError(str(kind))
        var = self.src.fresh("a")
        prim = sub[0] == Nodetype.BASE and sub[1][0] in FORMATS
        self.emit(f"{var} = array({value}, {self.src.dtype(sub[1][0])})" if prim else f"{var} = {value}")
        if kind == Nodetype.ARRAY:
            self.emit(f"if len({var}) != {length}:")
            self.emit(f"    raise ValueError(f'array of {{len({var})}} items where the type has {length}')")
        else:
            self.scalar(f"len({var})", "uint32")
            self.flush()
        if prim:
            size = _size(sub[1][0])
            if kind == Nodetype.ARRAY:
                self.align(size)
            elif size > self.g:
                self.emit(f"if len({var}):")
                self.align_code(size, "    ")
            self.emit(f"out.append({var})")
            self.emit(f"pos += {var}.nbytes")
            self.g = _after(self.g, length * size) if kind == Nodetype.ARRAY else min(self.g, size)
            return
        item = self.item_writer(sub)
        self.emit(f"for item in {var}:")
        self.emit(f"    pos = {item}(item, out, pos)")
        self.g = 1

    def item_writer(self, sub: tuple) -> str:
        if sub[0] == Nodetype.BASE:
            if sub[1][0] != "string":
                raise UnsupportedTypeError(sub[1][0])
            return "string_se"
        if sub[0] != Nodetype.NAME:
            raise UnsupportedTypeError(str(sub[0]))
        key = ("se", sub[1])
        if key not in self.src.helpers:
            name = self.src.helpers[key] = self.src.fresh("se_")
            body = _Writer(self.src, f"def {name}(msg, out, pos):", 1)
            body.message(sub[1], "msg")
            body.flush()
            body.emit("return pos")
            self.src.funcs.append(body.lines)
        return self.src.helpers[key]


def reader(store: Any, msgtype: str) -> Callable[[bytes], tuple[Any, int]]:
    """``read(payload) -> (message, end)`` for a little-endian CDR payload (any bytes-like object,
    its header already checked); ``end``: where the message ended in it. Raises
    UnsupportedTypeError for a type with fields it does not handle."""
    src = _Source(store)
    body = _Reader(src, "def read(buf):", 8)
    body.emit("pos = 4")
    obj = body.message(msgtype)
    body.flush()
    body.emit(f"return {obj}, pos")
    src.funcs.append(body.lines)
    return src.compile("read")


def decoder(store: Any, msgtype: str, error: type[Exception], other: Callable[[bytes], Any],
            pad_max: int) -> Callable[[bytes], Any]:
    """``decode(payload) -> message``: ``reader``'s code in one function with its checks around it
    (a subscription calls it per sample). A payload that is not little-endian CDR goes to
    ``other``; one the code cannot read, or with more than ``pad_max`` bytes after the message,
    raises ``error`` saying why."""
    src = _Source(store)
    src.ns.update(LE=HEADER_LE[:2], error=error, other=other, MSGTYPE=msgtype)
    body = _Reader(src, "def decode(buf):", 8)
    body.emit("if buf[:2] != LE:")
    body.emit("    return other(buf)")
    body.emit("try:")
    body.indent = "        "
    body.emit("pos = 4")
    obj = body.message(msgtype)
    body.flush()
    body.emit(f"msg = {obj}")
    body.indent = "    "
    body.emit("except Exception as exc:  # the code raises several types on truncated or garbage input")
    body.emit("    raise error(f'payload of {len(buf)} bytes is not a valid {MSGTYPE}: {exc}') from exc")
    body.emit(f"if pos + {pad_max} < len(buf):")
    body.emit("    raise error(f'payload of {len(buf)} bytes is not a valid {MSGTYPE}: '")
    body.emit("                f'{len(buf) - pos} bytes beyond the message')")
    body.emit("return msg")
    src.funcs.append(body.lines)
    return src.compile("decode")


def writer(store: Any, msgtype: str) -> Callable[[Any], tuple[list, int]]:
    """``write(msg) -> (pieces, size)``: the little-endian CDR payload of ``msg``, header included,
    as bytes-like pieces to join or copy in order, and its size in bytes."""
    src = _Source(store)
    body = _Writer(src, "def write(msg):", 8)
    body.emit("out = [HEADER]")
    body.emit("pos = 0")
    src.ns["HEADER"] = HEADER_LE
    body.message(msgtype, "msg")
    body.flush()
    body.emit("return out, pos + 4")
    src.funcs.append(body.lines)
    return src.compile("write")
