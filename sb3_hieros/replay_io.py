"""Replay files of HIEROS without pickle: every level's arrays as ``.npy`` members of a zip, with a JSON header.

``HIEROS.save_replay_buffer`` writes (format ``sb3_hieros.replay``, version 1):

* ``header.json``: for every level (level 0 first) the buffer class, every plain attribute (capacities, ``n_envs``,
  ``batch_length``, ``subgoal_shape``, ``context_dim``, the write heads ``pos``/``full``, the ETBS ``temperature``
  and ``mode``, the samplers' settings) and a table of its arrays (member, dtype, shape);
* ``level<i>/<name>.npy``: the arrays in numpy's ``.npy`` format, written and read without pickled objects:
  observations (one member per key of a Dict space), actions, rewards, ``is_first``, ``is_terminal``, subgoals, the
  replay context and ``has_context``, the per-stream write heads ``stream_pos``/``stream_full``/``_expect_first``, and
  the draw counters of the ``count`` mode;
* ``hieros_manifest.json``: the sha256 of every member (:mod:`sb3_hieros.save_util`).

The archive is a valid ``.npz`` (``numpy.load`` lists the arrays). Spaces and the device are not stored: a replay is
loaded into a model whose buffers have the same layout, and takes them from there.

:func:`read_replay` validates the whole file against the model's current buffers (levels, classes, ``n_envs``, rows
per stream, every array's dtype and shape, the write heads) before it reads a byte of array data, then builds new
buffer objects; the caller swaps them in only when everything succeeded. A pickle written by earlier versions (SB3's
``save_replay_buffer``) still loads, with a warning, through the same validation.
"""

from __future__ import annotations

import copy
import hashlib
import io
import json
import pathlib
import pickle
import warnings
import zipfile
import zlib
from collections.abc import Mapping, Sequence
from typing import Any, BinaryIO

import numpy as np

from sb3_hieros.buffers import SequenceReplayBuffer
from sb3_hieros.save_util import HashingReader, check_digest, qualified_name, read_manifest

__all__ = ["FORMAT", "read_replay", "write_replay"]

FORMAT = "sb3_hieros.replay"
VERSION = 1
HEADER_NAME = "header.json"
_ZIP_MAGIC = b"PK\x03\x04"
#: attributes taken from the model's buffers, never from a file
_SKIPPED = ("observation_space", "action_space", "device", "higher_levels")
#: arrays of nested objects that are state (the others are derived from their settings and not stored)
_NESTED_STATE = {"counter": ("counts",)}
#: plain attributes that are state (the others are settings and come from the model)
_STATE_VALUES = ("pos", "full")


def _plain(value: Any) -> tuple[bool, Any]:
    """Whether ``value`` is plain JSON data (numbers, strings, None, and lists/tuples/dicts of them), and its JSON
    form (numpy scalars become Python numbers)."""
    if value is None or isinstance(value, bool | int | float | str):
        return True, value
    if isinstance(value, np.bool_ | np.integer | np.floating):
        return True, value.item()
    if isinstance(value, list | tuple):
        items = [_plain(v) for v in value]
        return all(ok for ok, _ in items), [v for _, v in items]
    if isinstance(value, dict) and all(isinstance(k, str) for k in value):
        items = {k: _plain(v) for k, v in value.items()}
        return all(ok for ok, _ in items.values()), {k: v for k, (_, v) in items.items()}
    return False, None


def _describe(obj: Any, member_prefix: str) -> tuple[dict[str, Any], list[tuple[dict[str, Any], np.ndarray]]]:
    """Header entry and ``(array spec, array)`` pairs of a buffer.

    :param obj: a replay buffer
    :param member_prefix: zip folder of its arrays (``level<i>``)
    :return: the entry (``class``, ``values``, ``objects``, ``arrays``) and its arrays
    """
    values: dict[str, Any] = {}
    objects: dict[str, Any] = {}
    arrays: list[tuple[dict[str, Any], np.ndarray]] = []

    def add(name: str, key: str | None, array: np.ndarray) -> None:
        member = f"{member_prefix}/{name}{'' if key is None else f'/{len(arrays)}'}.npy"
        spec = {"name": name, "key": key, "member": member, "dtype": array.dtype.str, "shape": list(array.shape)}
        arrays.append((spec, array))

    for name, value in vars(obj).items():
        if name in _SKIPPED:
            continue
        ok, plain = _plain(value)
        if ok:
            values[name] = plain
        elif isinstance(value, np.ndarray):
            add(name, None, value)
        elif isinstance(value, dict) and value and all(isinstance(v, np.ndarray) for v in value.values()):
            for key, array in value.items():  # Dict observations: one member per key
                add(name, str(key), array)
        elif name in ("counter", "meanfield"):  # the ETBS buffer's samplers: settings, and the draw counters
            nested: dict[str, Any] = {}
            for field, item in vars(value).items():
                if field in _NESTED_STATE.get(name, ()):
                    add(f"{name}.{field}", None, item)
                    continue
                ok, plain = _plain(item)
                if ok:
                    nested[field] = plain
            objects[name] = {"class": qualified_name(type(value)), "values": nested}
        else:
            raise TypeError(
                f"{type(obj).__name__}.{name} ({type(value).__name__}) has no pickle-free form; replay buffers with "
                "such attributes cannot be saved by HIEROS"
            )
    entry = {"class": qualified_name(type(obj)), "values": values, "objects": objects, "arrays": [s for s, _ in arrays]}
    return entry, arrays


def write_replay(target: pathlib.Path | BinaryIO, buffers: Sequence[SequenceReplayBuffer]) -> None:
    """Write the replay of every level (level 0 first) as a zip of ``.npy`` members and ``header.json``.

    :param target: the file (path or binary file object) to write; :func:`sb3_hieros.save_util.write_archive` adds the
        manifest and makes the write atomic
    :param buffers: the buffers, level 0 first
    """
    with zipfile.ZipFile(target, "w", zipfile.ZIP_STORED, allowZip64=True) as archive:
        levels = []
        for i, buffer in enumerate(buffers):
            entry, arrays = _describe(buffer, f"level{i}")
            for spec, array in arrays:
                with archive.open(spec["member"], "w", force_zip64=True) as member:
                    np.lib.format.write_array(member, np.ascontiguousarray(array), allow_pickle=False)
            levels.append(entry)
        header = {"format": FORMAT, "version": VERSION, "levels": levels}
        archive.writestr(HEADER_NAME, json.dumps(header, indent=1))


# ------------------------------------------------------------------------------------------------ validation


def _template_arrays(buffer: SequenceReplayBuffer) -> dict[tuple[str, str | None], np.ndarray]:
    """The state arrays of a model's buffer by ``(name, key)``, as a file must hold them."""
    _, arrays = _describe(buffer, "")
    return {(spec["name"], spec["key"]): array for spec, array in arrays}


def _check_level(i: int, entry: Any, template: SequenceReplayBuffer, label: str) -> None:
    """Raise ``ValueError`` unless header entry ``entry`` fits the model's level-``i`` buffer ``template``."""
    if not isinstance(entry, dict) or not all(k in entry for k in ("class", "values", "arrays")):
        raise ValueError(f"{label}: the header entry of level {i} is malformed")
    values = entry["values"]
    if entry["class"] != qualified_name(type(template)):
        raise ValueError(
            f"{label}: level {i} holds a {entry['class']}, but this model's level-{i} replay is a "
            f"{qualified_name(type(template))}"
        )
    if values.get("n_envs") != template.n_envs:
        raise ValueError(
            f"{label} holds a replay of {values.get('n_envs')} envs, but this model has n_envs={template.n_envs}"
        )
    if values.get("buffer_size") != template.buffer_size:
        raise ValueError(
            f"{label}: level {i} holds {values.get('buffer_size')} rows per env stream, but this model's level-{i} "
            f"replay has {template.buffer_size} (buffer_size // n_envs); load the model with the buffer_size it was "
            "saved with"
        )
    if not isinstance(values.get("pos"), int) or not isinstance(values.get("full"), bool):
        raise ValueError(f"{label}: level {i} has no valid write head (pos={values.get('pos')!r})")
    expected = {name: (array.dtype.str, list(array.shape)) for name, array in _template_arrays(template).items()}
    specs = entry["arrays"]
    found = {(s.get("name"), s.get("key")): (s.get("dtype"), s.get("shape")) for s in specs if isinstance(s, dict)}
    if found.keys() != expected.keys() or len(found) != len(specs):
        missing = sorted(f"{n}[{k}]" if k else n for n, k in expected.keys() - found.keys())
        extra = sorted(f"{n}[{k}]" if k else str(n) for n, k in found.keys() - expected.keys())
        raise ValueError(
            f"{label}: level {i} does not hold the arrays of this model's replay (missing: {missing}, unexpected: "
            f"{extra}); was it saved with other settings (replay_context, n_levels, replay mode)?"
        )
    for name, (dtype, shape) in expected.items():
        if found[name] != (dtype, shape):
            got_dtype, got_shape = found[name]
            label_name = f"{name[0]}[{name[1]}]" if name[1] else name[0]
            raise ValueError(
                f"{label}: level {i} array {label_name!r} has dtype {got_dtype} and shape {tuple(got_shape or ())}, "
                f"this model's replay needs {dtype} and {tuple(shape)} (other observation or action space?)"
            )


def _check_heads(i: int, buffer: SequenceReplayBuffer, label: str) -> None:
    """Raise ``ValueError`` unless the write heads of a restored buffer lie inside its streams."""
    heads = buffer.stream_pos
    if heads.min(initial=0) < 0 or heads.max(initial=0) >= buffer.buffer_size:
        raise ValueError(
            f"{label}: level {i} has write heads {heads.tolist()} outside the {buffer.buffer_size} rows of a stream"
        )
    if buffer.pos != int(heads[0]) or buffer.full != bool(buffer.stream_full[0]):
        raise ValueError(f"{label}: level {i} has a write head pos={buffer.pos} that differs from its stream 0")


def _restore(
    header: Mapping[str, Any], arrays: Mapping[str, np.ndarray], templates: Sequence[SequenceReplayBuffer], label: str
) -> list[SequenceReplayBuffer]:
    """New buffers: the model's buffers (settings, spaces, device) with the state of the file."""
    restored = []
    for i, (entry, template) in enumerate(zip(header["levels"], templates, strict=True)):
        buffer = copy.copy(template)
        nested: dict[str, Any] = {}  # samplers (copies of the model's) and Dict observations, by attribute
        for spec in entry["arrays"]:
            name, key, array = spec["name"], spec["key"], arrays[spec["member"]]
            if "." in name:
                owner, field = name.split(".", 1)
                setattr(nested.setdefault(owner, copy.copy(getattr(template, owner))), field, array)
            elif key is not None:
                nested.setdefault(name, {})[key] = array
            else:
                setattr(buffer, name, array)
        for name, value in nested.items():
            setattr(buffer, name, value)
        for name in _STATE_VALUES:
            setattr(buffer, name, entry["values"][name])
        _check_heads(i, buffer, label)
        restored.append(buffer)
    restored[0].higher_levels = restored[1:]  # type: ignore[attr-defined]
    return restored


def _check_levels(header: Any, templates: Sequence[SequenceReplayBuffer], label: str) -> None:
    levels = header.get("levels") if isinstance(header, dict) else None
    if not isinstance(levels, list):
        raise ValueError(f"{label}: its header lists no levels")
    if len(levels) != len(templates):
        raise ValueError(
            f"{label} holds the replay of {len(levels)} levels, but this model keeps {len(templates)} replays (one per "
            "level with a world model)"
        )
    for i, (entry, template) in enumerate(zip(levels, templates, strict=True)):
        _check_level(i, entry, template, label)


# ------------------------------------------------------------------------------------------------ reading


def _read_array(archive: zipfile.ZipFile, spec: Mapping[str, Any], expected: Any, label: str) -> np.ndarray:
    """Read one ``.npy`` member (no pickled objects) whose dtype and shape must be those of ``spec``; its sha256
    must be ``expected``."""
    name = spec["member"]
    try:
        with archive.open(name) as member:
            reader = HashingReader(member)
            version = np.lib.format.read_magic(reader)
            fmt = np.lib.format
            read_header = fmt.read_array_header_1_0 if version == (1, 0) else fmt.read_array_header_2_0
            shape, fortran, dtype = read_header(reader)
            if list(shape) != list(spec["shape"]) or dtype.str != spec["dtype"] or fortran or dtype.hasobject:
                raise ValueError(
                    f"its .npy header says {dtype.str} {shape}, the header.json {spec['dtype']} {tuple(spec['shape'])}"
                )
            array = np.empty(shape, dtype=dtype)
            view = memoryview(array.reshape(-1).view(np.uint8))
            filled = 0
            while filled < len(view):
                n = reader.readinto(view[filled:])
                if not n:
                    raise ValueError(f"it ends after {filled} of {len(view)} bytes of array data")
                filled += n
            if reader.drain():
                raise ValueError("it holds more bytes than its array")
    except (ValueError, zipfile.BadZipFile, zlib.error, EOFError, OSError) as err:
        raise ValueError(f"{label}: member {name!r} is corrupted ({type(err).__name__}: {err})") from None
    check_digest(name, expected, reader.sha256.hexdigest(), label)
    return array


def _read_zip(file: BinaryIO, templates: Sequence[SequenceReplayBuffer], label: str) -> list[SequenceReplayBuffer]:
    try:
        with zipfile.ZipFile(file) as archive:
            manifest = read_manifest(archive, label)
            if manifest is None or HEADER_NAME not in archive.namelist():
                raise ValueError(f"{label} is a zip but not a HIEROS replay (no {HEADER_NAME!r} and manifest)")
            sums = manifest["sha256"]
            raw = archive.read(HEADER_NAME)
            check_digest(HEADER_NAME, sums.get(HEADER_NAME), hashlib.sha256(raw).hexdigest(), label)
            header = json.loads(raw.decode())
            if not isinstance(header, dict) or header.get("format") != FORMAT or header.get("version") != VERSION:
                raise ValueError(f"{label} is not a HIEROS replay of format {FORMAT} version {VERSION}")
            _check_levels(header, templates, label)
            specs = [spec for entry in header["levels"] for spec in entry["arrays"]]
            members = {spec["member"] for spec in specs}
            if len(members) != len(specs) or members != set(sums) - {HEADER_NAME}:
                raise ValueError(f"{label}: its members do not match its header (members added or removed?)")
            arrays = {spec["member"]: _read_array(archive, spec, sums[spec["member"]], label) for spec in specs}
    except (zipfile.BadZipFile, zlib.error, EOFError, UnicodeDecodeError, json.JSONDecodeError) as err:
        raise ValueError(f"{label} is not a readable HIEROS replay (truncated or corrupted?): {err}") from None
    return _restore(header, arrays, templates, label)


def _read_pickle(file: BinaryIO, templates: Sequence[SequenceReplayBuffer], label: str) -> list[SequenceReplayBuffer]:
    warnings.warn(
        f"{label} is a pickled replay (written by sb3-hieros before its pickle-free format): unpickling runs any code "
        "the file names, so load only pickles you trust; save_replay_buffer now writes the pickle-free format",
        UserWarning,
        stacklevel=3,
    )
    try:
        buffer = pickle.load(file)  # the documented legacy path, after the warning
    except (pickle.UnpicklingError, EOFError, AttributeError, ImportError, IndexError, TypeError) as err:
        raise ValueError(f"{label} is not a readable replay pickle: {type(err).__name__}: {err}") from None
    higher = getattr(buffer, "higher_levels", None)
    if not isinstance(buffer, SequenceReplayBuffer) or not isinstance(higher, list):
        raise ValueError(f"{label} does not hold a HIEROS replay (SequenceReplayBuffer with higher_levels)")
    levels, arrays = [], {}
    try:
        for i, level in enumerate([buffer, *higher]):
            entry, pairs = _describe(level, f"level{i}")
            levels.append(entry)
            arrays.update({spec["member"]: array for spec, array in pairs})
    except TypeError as err:
        raise ValueError(f"{label}: {err}") from None
    header = {"levels": levels}
    _check_levels(header, templates, label)
    return _restore(header, arrays, templates, label)


def read_replay(
    path: str | pathlib.Path | io.BufferedIOBase, templates: Sequence[SequenceReplayBuffer]
) -> list[SequenceReplayBuffer]:
    """Read a replay file (zip, or a legacy pickle with a warning) into new buffers shaped like ``templates``.

    Nothing of ``templates`` changes: the caller swaps the returned buffers in. Any mismatch or corruption raises
    ``ValueError`` naming the level and the array or member.

    :param path: the file (``.pkl`` is tried when a path without suffix does not exist) or a binary file object
    :param templates: the model's current buffers, level 0 first (settings, spaces and device are taken from them)
    :return: the restored buffers, level 0 first, with ``higher_levels`` set on level 0
    """
    if isinstance(path, str | pathlib.Path):
        path = pathlib.Path(path)
        if not path.exists() and path.suffix == "" and pathlib.Path(f"{path}.pkl").exists():
            path = pathlib.Path(f"{path}.pkl")
        with path.open("rb") as file:
            return _read_file(file, templates, str(path))
    return _read_file(path, templates, str(path))  # type: ignore[arg-type]


def _read_file(file: BinaryIO, templates: Sequence[SequenceReplayBuffer], label: str) -> list[SequenceReplayBuffer]:
    start = file.tell()
    magic = file.read(4)
    file.seek(start)
    if magic == _ZIP_MAGIC:
        return _read_zip(file, templates, label)
    if magic[:1] == b"\x80":
        return _read_pickle(file, templates, label)
    raise ValueError(f"{label} is neither a HIEROS replay zip nor a replay pickle (it starts with {magic!r})")
