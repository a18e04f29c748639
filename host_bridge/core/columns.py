"""A run of CDR payloads of one type read as numpy columns, with no Python per message.

Most high-rate ROS types have a fixed CDR layout once the lengths of their strings and sequences
are known (Imu, Odometry, TwistStamped, NavSatFix, JointState with one list of joints, TFMessage
with one transform, std_msgs numbers): every payload of a run whose length prefixes hold the same
values is laid out the same, so the run's payloads of that layout are rows of one 2-D byte array and
a numpy structured dtype (one field per number, at the offset the layout gives it) turns every
number field into a column at once. :func:`read_columns` does this for any type the typestore
knows, from its field list (no code per type):

1. The payloads are split by length and each length's are gathered into one 2-D byte array. A
   bag's run comes as :class:`PackedPayloads` (slices of one buffer: no object per payload, the
   gather reads them in place); a list of payloads is joined first (``b"".join`` runs in C).
2. For each length, one payload is walked in Python with CDR's rules (each number aligned to its
   size, at most 8, counted from the end of the 4-byte encapsulation header; a string or sequence
   length is a uint32 aligned to 4; the elements of an empty sequence are not aligned; at most 3
   bytes may follow the message), noting where each number and string lies and the offsets of the
   length prefixes it read. Every payload of that length whose header and length prefixes hold the
   same bytes has the same layout (each prefix's offset depends only on the prefixes before it), a
   comparison numpy makes for all of them at once; the others are walked in turn the same way.
   Layouts are remembered per type and typestore (up to 64), so the next run of a topic walks
   nothing: it only compares those bytes.
3. Strings come out once per block: the string bytes of a layout's rows are compared with its
   first row, and only where they differ are the rows split by their distinct strings.

The result equals rosbags' ``deserialize_cdr`` value by value, bitwise for floats (number types
as rosbags reads them: ``byte`` is int8, ``char`` uint8), and a run any of whose payloads rosbags
would refuse (bad header, truncated, unterminated string, bad UTF-8, more than 3 trailing bytes)
gives ``None``, so the caller's per-message fallback reports that one message as it does now.

How a converter's run form uses it (the dispatcher decodes each message today)::

    store = decoder.typestore_for(run[0].msgtype, run[0].definition)
    columns = read_columns([raw.data for raw in run], run[0].msgtype, store)
    if columns is None:  # a layout per message, a ragged nesting, or a payload rosbags refuses
        msgs = [decoder.decode(raw) for raw in run]  # and the message-object path as today
    else:
        stamps = columns["header.stamp.sec"].astype(np.int64) * 1_000_000_000
        stamps += columns["header.stamp.nanosec"]
        rates = np.stack([columns[f"angular_velocity.{a}"] for a in "xyz"], axis=1)  # (n, 3)
        for block in columns.blocks:  # rows sharing their strings: one frame per block
            frame = ctx.frame(block.strings["header.frame_id"])
            ...  # rr.send_columns of block.rows' stamps and values

Paths are the dotted field names. A number field has shape ``(n, *dims)``, where ``dims`` holds
one entry for each array or sequence of messages on its way (``transforms.transform.translation.x``
of TFMessage is ``(n, k)``) and, for an array or sequence of numbers, its length last
(``position`` of JointState is ``(n, joints)``). Strings are per block: ``str``, or nested tuples of
that shape. A run that needs more blocks than :data:`MESSAGES_PER_BLOCK` allows, or where one
message's nested sequences differ in length (not a rectangle), also gives ``None``.
"""

from __future__ import annotations

import functools
import itertools
import struct
import weakref
from collections import defaultdict
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass
from typing import Any, TypeAlias, overload

import numpy as np
import numpy.typing as npt
from numpy.lib.stride_tricks import as_strided
from rosbags.interfaces import Nodetype
from rosbags.typesys.base import normalize_fieldname
from rosbags.typesys.store import Typestore

from host_bridge.errors import ConvertError

ENCAPSULATION = 4
"""Bytes of the CDR encapsulation header; alignment counts from its end."""

MESSAGES_PER_BLOCK = 16
"""A run is read in columns while it has at most one block per this many messages (plus one): a
new layout costs about what rosbags takes to decode 15 small messages one by one, a remembered
one about 3."""

_KEPT_LAYOUTS = 64  # layouts remembered per type
_MAX_TRAILING = 3  # rosbags refuses a payload with more bytes after the message
_LITTLE_ENDIAN = b"\x00\x01"
_BIG_ENDIAN = b"\x00\x00"

# The numpy type rosbags gives each ROS number type (rosbags.serde.utils.ndtype and primitives).
_NUMBER_CODES = {
    "bool": "?",  # read as bytes, then != 0 like rosbags' struct "?"
    "byte": "i1",
    "char": "u1",
    "int8": "i1",
    "uint8": "u1",
    "int16": "i2",
    "uint16": "u2",
    "int32": "i4",
    "uint32": "u4",
    "int64": "i8",
    "uint64": "u8",
    "float32": "f4",
    "float64": "f8",
}
_BOOL = "?"
_STRING_SIZE = 5  # the least bytes a string takes in a sequence (rosbags' check_sequence)

StringValue: TypeAlias = "str | tuple[StringValue, ...]"


class _NotColumnarError(Exception):
    """The run cannot be read in columns (the caller decodes it message by message)."""


@dataclass(frozen=True, slots=True)
class _Field:
    """One field of a message type, compiled from rosbags' field list.

    ``kind`` is ``number``, ``string`` or ``message``; ``length`` is a fixed array's length;
    ``chain`` the paths of the arrays and sequences from the root down to this field (itself
    included when it is one), which give a column its dimensions.
    """

    path: str
    kind: str
    code: str
    size: int
    members: tuple[_Field, ...]
    length: int | None
    sequence: bool
    chain: tuple[str, ...]

    @property
    def repeated(self) -> bool:
        return self.sequence or self.length is not None

    @property
    def least_element_size(self) -> int:
        """rosbags' bound on a sequence's length: every element takes at least this."""
        return {"number": self.size, "string": _STRING_SIZE}.get(self.kind, 1)


def _compile(store: Typestore, msgtype: str, prefix: str, chain: tuple[str, ...]) -> tuple[_Field, ...]:
    fields = []
    # The field list only: get_msgdef would have rosbags generate the type's 7 codecs too.
    for raw_name, desc in store.fielddefs[msgtype][1]:
        name = normalize_fieldname(raw_name)
        path = f"{prefix}{name}"
        node, arg, length, sequence = _element(desc)
        own_chain = (*chain, path) if sequence or length is not None else chain
        if node == Nodetype.NAME:
            members = _compile(store, arg, f"{path}.", own_chain)
            fields.append(_Field(path, "message", "", 0, members, length, sequence, own_chain))
        elif arg[0] == "string":
            fields.append(_Field(path, "string", "", 0, (), length, sequence, own_chain))
        elif arg[0] in _NUMBER_CODES:
            code = _NUMBER_CODES[arg[0]]
            size = np.dtype(code).itemsize
            fields.append(_Field(path, "number", code, size, (), length, sequence, own_chain))
        else:
            msg = f"{msgtype}.{name} is a {arg[0]}, which has no numpy column"
            raise _NotColumnarError(msg)
    return tuple(fields)


def _element(desc: Any) -> tuple[Nodetype, Any, int | None, bool]:
    """A rosbags field description as (node type, argument, fixed length, is a sequence), where
    the node type and argument are the element's for an array or sequence."""
    node, arg = desc
    if node == Nodetype.ARRAY:
        (element, element_arg), length = arg
        return element, element_arg, length, False
    if node == Nodetype.SEQUENCE:
        (element, element_arg), _bound = arg  # rosbags checks no bound when reading either
        return element, element_arg, None, True
    return node, arg, None, False


class _Plan:
    """A type compiled for columns: its fields, and the layouts its payloads had (by payload
    length), so a topic's runs walk a layout once, not once a run."""

    def __init__(self, fields: tuple[_Field, ...]) -> None:
        self.fields = fields
        leaves = list(_leaves(fields))
        self.numbers = [leaf for leaf in leaves if leaf.kind == "number"]
        self.strings = [leaf for leaf in leaves if leaf.kind == "string"]
        self._layouts: dict[int, list[_Layout]] = {}

    def layouts(self, length: int) -> list[_Layout]:
        return list(self._layouts.get(length, ()))

    def remember(self, layout: _Layout) -> None:
        if sum(map(len, self._layouts.values())) >= _KEPT_LAYOUTS:
            self._layouts.clear()  # a type whose layouts keep changing (free text) starts over
        self._layouts.setdefault(layout.length, []).append(layout)


def _leaves(fields: tuple[_Field, ...]) -> Iterator[_Field]:
    """The number and string fields, nested messages' included, in walk order."""
    for field in fields:
        if field.kind == "message":
            yield from _leaves(field.members)
        else:
            yield field


_PLANS: weakref.WeakKeyDictionary[Typestore, dict[str, _Plan | str]] = weakref.WeakKeyDictionary()


def _plan(store: Typestore, msgtype: str) -> _Plan:
    """The plan of ``msgtype`` (kept per typestore, like rosbags' own generated functions)."""
    plans = _PLANS.setdefault(store, {})
    plan = plans.get(msgtype)
    if plan is None:
        try:
            plan = _Plan(_compile(store, msgtype, "", ()))
        except _NotColumnarError as err:
            plan = str(err)
        plans[msgtype] = plan
    if isinstance(plan, str):
        raise _NotColumnarError(plan)
    return plan


def _align(pos: int, alignment: int) -> int:
    return (pos + alignment - 1) & -alignment


Slot = tuple[tuple[int, ...], int, int]
"""Where one value lies: its index among the arrays of messages on its way, its payload offset,
and its element count (numbers) or byte length with the terminator (strings)."""


class _Walk:
    """One payload walked with CDR's rules: where each value lies, the lengths read on the way."""

    def __init__(self, payload: bytes, fields: tuple[_Field, ...], max_sequence: int) -> None:
        header = payload[:2]
        if len(payload) < ENCAPSULATION or header not in (_LITTLE_ENDIAN, _BIG_ENDIAN):
            raise _NotColumnarError("not CDR: the encapsulation header is neither little nor big endian")
        self.byte_order = "<" if header == _LITTLE_ENDIAN else ">"
        self._payload = payload
        self._size = len(payload) - ENCAPSULATION
        self._uint32 = struct.Struct(f"{self.byte_order}I")
        self._max_sequence = max_sequence
        self.prefixes: list[int] = []
        """Payload offsets of the uint32 lengths read (strings, sequences)."""
        self.numbers: dict[str, list[Slot]] = defaultdict(list)
        self.strings: dict[str, list[Slot]] = defaultdict(list)
        self.counts: dict[tuple[str, tuple[int, ...]], int] = {}
        end = self._fields(fields, 0, ())
        if self._size - end > _MAX_TRAILING:
            msg = f"{self._size - end} bytes follow the message"
            raise _NotColumnarError(msg)

    def _length_prefix(self, pos: int) -> int:
        if pos + 4 > self._size:
            raise _NotColumnarError("truncated: a length runs past the payload")
        self.prefixes.append(ENCAPSULATION + pos)
        value: int = self._uint32.unpack_from(self._payload, ENCAPSULATION + pos)[0]
        return value

    def _fields(self, fields: tuple[_Field, ...], pos: int, index: tuple[int, ...]) -> int:
        for field in fields:
            count = field.length
            if field.sequence:
                pos = _align(pos, 4)
                count = self._length_prefix(pos)
                pos += 4
                if count > self._max_sequence or pos + count * field.least_element_size > self._size:
                    msg = f"{field.path} claims {count} elements, more than the payload holds"
                    raise _NotColumnarError(msg)
            if count is not None:
                self.counts[field.path, index] = count
            if field.kind == "number":
                pos = self._number(field, pos, index, count)
            elif field.kind == "string":
                for element in range(1 if count is None else count):
                    pos = self._string(field, pos, index if count is None else (*index, element))
            elif count is None:
                pos = self._fields(field.members, pos, index)
            else:
                for element in range(count):
                    pos = self._fields(field.members, pos, (*index, element))
        return pos

    def _number(self, field: _Field, pos: int, index: tuple[int, ...], count: int | None) -> int:
        if count != 0:  # an empty sequence's elements are not aligned
            pos = _align(pos, field.size)
        end = pos + field.size * (1 if count is None else count)
        if end > self._size:
            msg = f"truncated: {field.path} runs past the payload"
            raise _NotColumnarError(msg)
        self.numbers[field.path].append((index, ENCAPSULATION + pos, 1 if count is None else count))
        return end

    def _string(self, field: _Field, pos: int, index: tuple[int, ...]) -> int:
        pos = _align(pos, 4)
        length = self._length_prefix(pos)
        if length < 1 or pos + 4 + length > self._size:
            msg = f"{field.path} has a bad string length {length}"
            raise _NotColumnarError(msg)
        self.strings[field.path].append((index, ENCAPSULATION + pos + 4, length))
        return pos + 4 + length

    def dims(self, field: _Field) -> tuple[int, ...]:
        """The lengths of the arrays and sequences on ``field``'s way; a rectangle or refused."""
        dims: list[int] = []
        indices: list[tuple[int, ...]] = [()]
        for container in field.chain:
            found = {self.counts[container, index] for index in indices}
            if len(found) > 1:
                msg = f"{container} differs in length within one message ({sorted(found)})"
                raise _NotColumnarError(msg)
            count = found.pop() if found else 0
            dims.append(count)
            indices = [(*index, element) for index in indices for element in range(count)]
        return tuple(dims)


@dataclass(frozen=True, slots=True)
class _NumberColumn:
    """How one number field's column comes out of a layout's structured dtype."""

    path: str
    names: tuple[str, ...]
    dims: tuple[int, ...]
    code: str


@dataclass(frozen=True, slots=True)
class _StringSpan:
    """One string field's place in a row of a layout's string bytes: each string's byte size."""

    path: str
    dims: tuple[int, ...]
    sizes: tuple[int, ...]


_GATHERED_SIGNATURES = 64
"""Up to this many payloads a layout's signature bytes are gathered at once (a signature has a
few dozen bytes: compared byte by byte, each costs a numpy call)."""


class _Layout:
    """Where every field lies in the payloads of one length whose header and length prefixes hold
    the bytes ``key`` at the offsets ``signature``: one payload walked, a structured dtype."""

    def __init__(self, payload: bytes, plan: _Plan, max_sequence: int) -> None:
        walk = _Walk(payload, plan.fields, max_sequence)
        self.length = len(payload)
        prefix_bytes = (np.array(walk.prefixes, dtype=np.intp)[:, None] + np.arange(4)).ravel()
        self.signature = np.concatenate([np.arange(2), prefix_bytes])
        self.key = np.frombuffer(payload, dtype=np.uint8)[self.signature]
        names: list[str] = []
        formats: list[Any] = []
        offsets: list[int] = []
        self._numbers: list[_NumberColumn] = []
        for field in plan.numbers:
            field_names = []
            for index, offset, count in walk.numbers[field.path]:
                if count:  # an empty sequence has no bytes to view
                    field_names.append(f"{field.path}{list(index)}")
                    code = f"{walk.byte_order}{'u1' if field.code == _BOOL else field.code}"
                    formats.append(code if not field.repeated else (code, (count,)))
                    offsets.append(offset)
            names.extend(field_names)
            self._numbers.append(_NumberColumn(field.path, tuple(field_names), walk.dims(field), field.code))
        self._dtype = np.dtype(
            {"names": names, "formats": formats, "offsets": offsets, "itemsize": self.length}
        )
        self._strings = [
            _StringSpan(field.path, walk.dims(field), tuple(size for _, _, size in walk.strings[field.path]))
            for field in plan.strings
        ]
        self._string_offsets = np.array(
            [byte for field in plan.strings for _, offset, size in walk.strings[field.path]
             for byte in range(offset, offset + size)],
            dtype=np.intp,
        )

    def matching(self, grid: npt.NDArray[np.uint8], rows: npt.NDArray[np.intp]) -> npt.NDArray[np.bool_]:
        """Which of ``grid``'s ``rows`` have this layout."""
        if len(rows) <= _GATHERED_SIGNATURES:  # a live message: one gather, a few bytes
            gathered: npt.NDArray[np.bool_] = (grid[rows[:, None], self.signature] == self.key).all(axis=1)
            return gathered
        # Byte by byte down the columns: a strided view of the grid each while every row is
        # asked about, not a gather of every row's signature (7 % of a small-message bag's run).
        candidates = grid if len(rows) == len(grid) else grid[rows]
        same = np.ones(len(rows), dtype=np.bool_)
        for column, value in zip(self.signature.tolist(), self.key.tolist(), strict=True):
            same &= candidates[:, column] == value
        return same

    def numbers(self, grid: npt.NDArray[np.uint8]) -> dict[str, npt.NDArray[Any]]:
        """Every number field of ``grid``'s payloads as a native-order column (rows, *dims),
        through one structured view of the bytes."""
        records = grid.view(self._dtype)[:, 0]
        columns: dict[str, npt.NDArray[Any]] = {}
        for column in self._numbers:
            shape = (len(grid), *column.dims)
            if not column.names:
                columns[column.path] = np.zeros(shape, dtype=column.code)
                continue
            code = "u1" if column.code == _BOOL else column.code
            if len(column.names) == 1:
                values = records[column.names[0]].astype(code)
            else:  # filled part by part (np.stack costs more than the copy for a few rows)
                first = records[column.names[0]]
                values = np.empty((len(grid), len(column.names), *first.shape[1:]), dtype=code)
                for part, name in enumerate(column.names):
                    values[:, part] = records[name]
            columns[column.path] = (values != 0 if column.code == _BOOL else values).reshape(shape)
        return columns

    def string_bytes(self, grid: npt.NDArray[np.uint8]) -> npt.NDArray[np.uint8]:
        """Every string's bytes (terminators included) of each payload, one row per payload."""
        return grid[:, self._string_offsets]

    def strings(self, row: npt.NDArray[np.uint8]) -> dict[str, StringValue]:
        """The string fields of one row of :meth:`string_bytes`."""
        strings: dict[str, StringValue] = {}
        start = 0
        for span in self._strings:
            texts = []
            for size in span.sizes:
                texts.append(_decode(row[start : start + size], span.path))
                start += size
            strings[span.path] = _nest(texts, span.dims)
        return strings


@dataclass(frozen=True, slots=True)
class Block:
    """Messages of a run that share one layout and every string value.

    ``rows`` are their positions in the run (ascending); ``numbers`` has one row per message,
    ``strings`` one value for them all.
    """

    rows: npt.NDArray[np.intp]
    numbers: Mapping[str, npt.NDArray[Any]]
    strings: Mapping[str, StringValue]


@dataclass(frozen=True, slots=True)
class Columns:
    """A run of ``size`` messages in columns, in :class:`Block` s (usually one)."""

    size: int
    blocks: tuple[Block, ...]

    @property
    def paths(self) -> tuple[str, ...]:
        first = self.blocks[0]
        return (*first.numbers, *first.strings)

    def groups(self, path: str) -> list[tuple[StringValue, npt.NDArray[np.intp]]]:
        """The run's rows per value of the string field ``path`` (a frame id, a joint list), in
        order of first appearance; rows ascending."""
        rows: dict[StringValue, list[npt.NDArray[np.intp]]] = {}
        for block in self.blocks:
            rows.setdefault(block.strings[path], []).append(block.rows)
        return [
            (value, parts[0] if len(parts) == 1 else np.sort(np.concatenate(parts)))
            for value, parts in rows.items()
        ]

    def __getitem__(self, path: str) -> npt.NDArray[Any]:
        """The field's column over the whole run, in run order: numbers as their numpy type,
        strings as an object array; ValueError when its shape differs between blocks (a topic
        whose JointStates name different joints): then read :attr:`blocks`."""
        first = self.blocks[0]
        if path in first.numbers:
            parts = [block.numbers[path] for block in self.blocks]
        elif path in first.strings:
            parts = [_string_array(block.strings[path], len(block.rows)) for block in self.blocks]
        else:
            msg = f"no field {path!r} (fields: {', '.join(self.paths)})"
            raise KeyError(msg)
        if len(parts) == 1:
            return parts[0]
        shapes = {part.shape[1:] for part in parts}
        if len(shapes) > 1:
            msg = f"{path} has shapes {sorted(shapes)} in different messages of the run: read its blocks"
            raise ValueError(msg)
        column = np.empty((self.size, *parts[0].shape[1:]), dtype=parts[0].dtype)
        for block, part in zip(self.blocks, parts, strict=True):
            column[block.rows] = part
        return column


def _string_array(value: StringValue, rows: int) -> npt.NDArray[np.object_]:
    """``rows`` copies of a block's string value as an object array of shape (rows, *dims)
    (element by element: numpy's own str arrays would drop trailing NULs rosbags keeps)."""
    texts: list[str] = []
    dims = _flatten(value, texts)
    one = np.empty(len(texts), dtype=object)
    for position, text in enumerate(texts):
        one[position] = text
    column: npt.NDArray[np.object_] = np.broadcast_to(one.reshape(dims), (rows, *dims)).copy()
    return column


def _flatten(value: StringValue, texts: list[str]) -> tuple[int, ...]:
    """Appends ``value``'s strings to ``texts`` in row-major order; returns its shape."""
    if isinstance(value, str):
        texts.append(value)
        return ()
    dims = [_flatten(item, texts) for item in value]
    return (len(value), *(dims[0] if dims else ()))


@dataclass(frozen=True, slots=True, eq=False)
class PackedPayloads(Sequence[bytes | memoryview]):
    """Payloads as slices of a few buffers, with no object per payload: the i-th is
    ``buffers[sources[i]][starts[i]:ends[i]]`` (bytes slices are copies, memoryview slices are
    not). A bag's window keeps its payloads in their decompressed chunks (or copies of the part
    it reads); :func:`read_columns` gathers a run's rows straight from the buffers."""

    buffers: Sequence[bytes | memoryview]
    sources: npt.NDArray[np.intp]
    starts: npt.NDArray[np.intp]
    ends: npt.NDArray[np.intp]

    @classmethod
    def of(cls, payloads: Sequence[bytes | memoryview]) -> PackedPayloads:
        """``payloads`` joined into one buffer."""
        ends = np.cumsum(np.fromiter(map(len, payloads), dtype=np.intp, count=len(payloads)))
        starts = np.concatenate([np.zeros(1, np.intp), ends[:-1]]) if len(ends) else ends
        return cls((b"".join(payloads),), np.zeros(len(payloads), np.intp), starts, ends)

    def __len__(self) -> int:
        return len(self.starts)

    @overload
    def __getitem__(self, index: int) -> bytes | memoryview: ...
    @overload
    def __getitem__(self, index: slice) -> PackedPayloads: ...
    def __getitem__(self, index: int | slice) -> bytes | memoryview | PackedPayloads:
        if isinstance(index, slice):
            return PackedPayloads(self.buffers, self.sources[index], self.starts[index], self.ends[index])
        payload: bytes | memoryview = self.buffers[self.sources[index]][self.starts[index] : self.ends[index]]
        return payload

    def __iter__(self) -> Iterator[bytes | memoryview]:
        buffers = self.buffers
        for source, start, end in zip(
            self.sources.tolist(), self.starts.tolist(), self.ends.tolist(), strict=True
        ):
            yield buffers[source][start:end]


def read_columns(
    payloads: Sequence[bytes | memoryview],
    msgtype: str,
    store: Typestore,
    *,
    max_blocks: int | None = None,
) -> Columns | None:
    """The run of CDR ``payloads`` (encapsulation header included) of ``msgtype``, as known to
    ``store``, in columns; ``None`` when it cannot be (see the module's docstring): decode it
    message by message then. ``max_blocks`` replaces the default bound on blocks. Payloads in
    one buffer (:class:`PackedPayloads`) are read in place, any others joined first."""
    if not payloads:
        return None
    packed = payloads if isinstance(payloads, PackedPayloads) else PackedPayloads.of(payloads)
    limit = 1 + len(payloads) // MESSAGES_PER_BLOCK if max_blocks is None else max_blocks
    blocks: list[Block] = []
    try:
        plan = _plan(store, msgtype)
        for rows, grid in _by_length(packed):
            for block in _blocks(plan, rows, grid, store.max_sequence_length):
                blocks.append(block)
                if len(blocks) > limit:
                    return None
    except _NotColumnarError:
        return None
    return Columns(len(payloads), tuple(sorted(blocks, key=lambda block: int(block.rows[0]))))


@functools.cache
def _message_store() -> Typestore:
    from host_bridge.core.schemas import base_typestore

    return base_typestore()


def columns_of_messages(msgs: Sequence[Any], topic: str) -> Columns:
    """Decoded messages of one type (``__msgtype__``, ROS 1 ones included) as the columns their
    CDR gives: serialized again with the bundled definitions and read as a run, any number of
    blocks allowed. For converters written against columns, called with messages (tests, a
    run the dispatcher decoded to find its bad message); not a fast path."""
    msgtype = msgs[0].__msgtype__
    store = _message_store()
    try:
        payloads = [store.serialize_cdr(msg, msgtype) for msg in msgs]
    except Exception as err:
        msg = f"{topic}: {msgtype} message does not serialize with the bundled definition: {err}"
        raise ConvertError(msg) from err
    columns = read_columns(payloads, msgtype, store, max_blocks=len(payloads))
    if columns is None:
        msg = f"{topic}: {msgtype} has nested sequences of differing lengths, not columns"
        raise ConvertError(msg)
    return columns


def _by_length(
    packed: PackedPayloads,
) -> Iterator[tuple[npt.NDArray[np.intp], npt.NDArray[np.uint8]]]:
    """The payloads split by length: their positions and a (rows, length) byte array, gathered
    from their buffers (a view where they lie back to back in one)."""
    buffers = [np.frombuffer(buffer, dtype=np.uint8) for buffer in packed.buffers]
    starts, lengths = packed.starts, packed.ends - packed.starts
    if (lengths == lengths[0]).all():
        groups: Iterator[tuple[npt.NDArray[np.intp], int]] = iter(
            [(np.arange(len(lengths)), int(lengths[0]))])
    else:
        values, which = np.unique(lengths, return_inverse=True)
        groups = ((np.flatnonzero(which == number), int(length)) for number, length in enumerate(values))
    for rows, length in groups:
        sources = packed.sources[rows]
        if (sources == sources[0]).all():
            yield rows, _rows_of(buffers[int(sources[0])], starts[rows], length)
            continue
        # A window's payloads come chunk after chunk: copied a stretch of one buffer at a time
        # (assigning through a boolean mask per buffer cost 8 % of a small-message bag's run).
        grid = np.empty((len(rows), length), dtype=np.uint8)
        stretches = [0, *(np.flatnonzero(sources[1:] != sources[:-1]) + 1).tolist(), len(rows)]
        for begin, end in itertools.pairwise(stretches):
            grid[begin:end] = _rows_of(buffers[int(sources[begin])], starts[rows[begin:end]], length)
        yield rows, grid


def _rows_of(
    buffer: npt.NDArray[np.uint8], starts: npt.NDArray[np.intp], length: int
) -> npt.NDArray[np.uint8]:
    """The ``length`` bytes at each of ``starts`` in ``buffer`` as rows: a view where they lie
    back to back, else one gather through a view of the buffer as its rows at every offset."""
    first = int(starts[0])
    if (starts == first + length * np.arange(len(starts))).all():
        return buffer[first : first + length * len(starts)].reshape(len(starts), length)
    at_every_byte = as_strided(buffer, (max(len(buffer) - length + 1, 0), length), (1, 1), writeable=False)
    rows: npt.NDArray[np.uint8] = at_every_byte[starts]
    return rows


def _blocks(
    plan: _Plan, rows: npt.NDArray[np.intp], grid: npt.NDArray[np.uint8], max_sequence: int
) -> Iterator[Block]:
    """Blocks of payloads of one length: the layouts seen before claim their payloads, then each
    unclaimed payload's layout claims every payload with the same header and length prefixes."""
    unclaimed = np.arange(len(rows))
    known = iter(plan.layouts(grid.shape[1]))
    while unclaimed.size:
        layout = next(known, None)
        if layout is None:
            layout = _Layout(grid[unclaimed[0]].tobytes(), plan, max_sequence)
            plan.remember(layout)
        same = layout.matching(grid, unclaimed)
        if not same.any():
            continue
        members = unclaimed[same]
        unclaimed = unclaimed[~same]
        members_grid = grid if members.size == len(rows) else grid[members]
        yield from _layout_blocks(layout, rows[members], members_grid)


def _layout_blocks(
    layout: _Layout, rows: npt.NDArray[np.intp], grid: npt.NDArray[np.uint8]
) -> Iterator[Block]:
    """Payloads of one layout as blocks, split only where their strings differ."""
    numbers = layout.numbers(grid)
    string_bytes = layout.string_bytes(grid)
    if (string_bytes == string_bytes[0]).all():
        yield Block(rows, numbers, layout.strings(string_bytes[0]))
        return
    distinct, which = np.unique(string_bytes, axis=0, return_inverse=True)
    which = which.reshape(-1)
    for number, value in enumerate(distinct):
        members = np.flatnonzero(which == number)
        yield Block(
            rows[members], {path: column[members] for path, column in numbers.items()}, layout.strings(value)
        )


def _decode(raw: npt.NDArray[np.uint8], path: str) -> str:
    if raw[-1] != 0:
        msg = f"{path} is a string without its terminator"
        raise _NotColumnarError(msg)
    try:
        return raw[:-1].tobytes().decode()
    except UnicodeDecodeError as err:
        msg = f"{path} is not UTF-8: {err}"
        raise _NotColumnarError(msg) from err


def _nest(texts: list[str], dims: tuple[int, ...]) -> StringValue:
    """Strings in walk order (row-major) as nested tuples of shape ``dims``."""
    if not dims:
        return texts[0]
    step = len(texts) // dims[0] if dims[0] else 0
    return tuple(_nest(texts[i * step : (i + 1) * step], dims[1:]) for i in range(dims[0]))
