"""Crash-safe writing, integrity checks and loading without unpickling, for the files HIEROS writes.

Atomic writes
-------------
:func:`write_archive` lets a writer fill a temporary file in the target's directory, adds the manifest, flushes the
file to disk (``fsync``), renames it over the target with ``os.replace`` and syncs the directory. A crash, a full
disk or ``kill -9`` at any moment leaves the target either as it was or complete, never partly written. When the
writer raises, the temporary file is removed and the target is untouched. A temporary file that a killed process left
behind (``.<name>.<random>.tmp`` next to the target) is removed by the next successful save to the same path; one
process should save to a path at a time.

Manifest
--------
Every zip HIEROS writes (model and replay) holds ``hieros_manifest.json``: the sha256 of every other member, checked
by :func:`verify_archive` before anything in the file is used. A member that changed after saving (bit rot, a
re-zipped archive with edited tensors) is refused naming the member. The checksums detect corruption and edits that
did not update the manifest; they are not a signature. The manifest also holds plain JSON values from which
:func:`safe_load_objects` rebuilds what SB3 stores as cloudpickle in the model's ``data`` member (the policy class,
the learning-rate schedule, the episode statistics).

Loading without unpickling
--------------------------
SB3 stores every attribute that JSON cannot hold (spaces, schedules, classes, numpy arrays) as a base64 cloudpickle
(``":serialized:"``) in the ``data`` member; unpickling it runs whatever code the file names. :func:`load_objects`
resolves every such entry once, before SB3's ``load`` sees the file, and hands the results to SB3 as
``custom_objects`` so that SB3 unpickles nothing more. With ``safe=True`` nothing is unpickled at all: the entries
are rebuilt from plain JSON values and from the environment passed in (:func:`safe_load_objects`). The tensors are
read by SB3 with ``torch.load(weights_only=True)`` in both modes, which does not run code.
"""

from __future__ import annotations

import base64
import collections
import contextlib
import hashlib
import io
import json
import math
import os
import pathlib
import secrets
import warnings
import zipfile
import zlib
from collections.abc import Callable, Collection, Iterator, Mapping
from typing import Any, BinaryIO

import cloudpickle
from gymnasium import spaces
from stable_baselines3.common.type_aliases import TrainFreq, TrainFrequencyUnit
from stable_baselines3.common.utils import ConstantSchedule, FloatSchedule, LinearSchedule

__all__ = [
    "MANIFEST_NAME",
    "HashingReader",
    "atomic_path",
    "load_objects",
    "plain_builders",
    "prepare_model_load",
    "qualified_name",
    "resolve_path",
    "safe_load_objects",
    "safe_load_values",
    "schedule_from_json",
    "schedule_to_json",
    "verify_archive",
    "write_archive",
]

#: zip member holding the checksums of every other member and the plain JSON values of safe loading
MANIFEST_NAME = "hieros_manifest.json"
MANIFEST_VERSION = 1
_CHUNK = 1 << 20
_SERIALIZED = ":serialized:"


# ------------------------------------------------------------------------------------------------ atomic writes


def resolve_path(path: str | pathlib.Path, suffix: str) -> pathlib.Path:
    """The file SB3's ``open_path`` writes for ``path``: ``.<suffix>`` appended when ``path`` has no suffix, and
    ``<path>_2`` (with a warning) when ``path`` is a directory.

    :param path: the path given to ``save``
    :param suffix: the default suffix without the dot (``"zip"``, ``"pkl"``)
    :return: the file to write
    """
    path = pathlib.Path(path)
    if path.suffix == "" and suffix:
        path = pathlib.Path(f"{path}.{suffix}")
    if path.is_dir():
        warnings.warn(f"Path '{path}' is a folder. Will save instead to {path}_2", stacklevel=3)
        path = pathlib.Path(f"{path}_2")
    return path


def _fsync(path: pathlib.Path, directory: bool = False) -> None:
    """Flush a file (or a directory entry) to disk; directories on file systems that cannot sync them are skipped."""
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    except OSError:
        if not directory:
            raise
    finally:
        os.close(fd)


@contextlib.contextmanager
def atomic_path(path: pathlib.Path) -> Iterator[pathlib.Path]:
    """A temporary path next to ``path`` that replaces ``path`` atomically once the ``with`` block ends normally.

    The block must write the temporary file completely and close it. Then the file is synced, renamed over ``path``
    (``os.replace``) and the directory synced; temporary files of earlier, killed saves to ``path`` are removed. If the
    block raises, the temporary file is removed and ``path`` is left as it was.

    :param path: the file to write (its directory is created if needed)
    :return: the temporary path to write to
    """
    directory = path.parent
    directory.mkdir(parents=True, exist_ok=True)
    prefix = f".{path.name}."
    tmp = directory / f"{prefix}{secrets.token_hex(6)}.tmp"
    tmp.open("xb").close()  # exclusive create: never another save's file
    try:
        yield tmp
        _fsync(tmp)
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    _fsync(directory, directory=True)
    for stale in directory.glob(f"{glob_escape(prefix)}*.tmp"):
        stale.unlink(missing_ok=True)


def glob_escape(text: str) -> str:
    """``text`` with the glob metacharacters ``*?[`` escaped (``glob.escape`` for ``pathlib.Path.glob``)."""
    return "".join(f"[{c}]" if c in "*?[" else c for c in text)


def _digest(archive: zipfile.ZipFile, name: str, label: str) -> str:
    """sha256 of member ``name`` (zip's CRC-32 check included), read in chunks."""
    digest = hashlib.sha256()
    try:
        with archive.open(name) as member:
            for chunk in iter(lambda: member.read(_CHUNK), b""):
                digest.update(chunk)
    except (zipfile.BadZipFile, zlib.error, EOFError, OSError) as err:
        raise ValueError(f"{label}: member {name!r} is corrupted ({type(err).__name__}: {err})") from None
    return digest.hexdigest()


def add_manifest(target: pathlib.Path | BinaryIO, extra: Mapping[str, Any] | None = None) -> None:
    """Append :data:`MANIFEST_NAME` (sha256 of every member plus ``extra``) to the zip ``target``.

    :param target: a finished zip file (path or seekable binary file)
    :param extra: plain JSON values to keep in the manifest
    """
    with zipfile.ZipFile(target, "a") as archive:
        names = archive.namelist()
        if MANIFEST_NAME in names:
            raise ValueError(f"the archive already holds a member {MANIFEST_NAME!r}")
        digests = {name: _digest(archive, name, str(target)) for name in names}
        manifest = {"version": MANIFEST_VERSION, "sha256": digests, **(extra or {})}
        archive.writestr(MANIFEST_NAME, json.dumps(manifest, indent=1, allow_nan=False))


def write_archive(
    path: str | pathlib.Path | io.BufferedIOBase,
    write: Callable[[Any], None],
    suffix: str,
    extra: Mapping[str, Any] | None = None,
) -> None:
    """Write a zip through ``write``, add the manifest and put the result at ``path`` atomically (module docstring).

    :param path: a file path (written atomically; ``.<suffix>`` appended when it has none) or a writable binary file
        object (written at its position once the archive is complete)
    :param write: fills a zip at the path or file object it is given
    :param suffix: default suffix of ``path``
    :param extra: plain JSON values for the manifest
    """
    if isinstance(path, str | pathlib.Path):
        with atomic_path(resolve_path(path, suffix)) as tmp:
            write(tmp)
            add_manifest(tmp, extra)
        return
    buffer = io.BytesIO()
    write(buffer)
    add_manifest(buffer, extra)
    path.write(buffer.getvalue())


# ------------------------------------------------------------------------------------------------ reading


class HashingReader(io.RawIOBase):
    """A readable stream that passes reads through and keeps the sha256 of everything read.

    :param stream: the stream to read
    """

    def __init__(self, stream: BinaryIO) -> None:
        super().__init__()
        self.stream = stream
        self.sha256 = hashlib.sha256()

    def readable(self) -> bool:
        return True

    def readinto(self, buffer: Any) -> int:
        view = memoryview(buffer).cast("B")
        data = self.stream.read(len(view))
        view[: len(data)] = data
        self.sha256.update(data)
        return len(data)

    def drain(self) -> int:
        """Read to the end; :return: the number of bytes that were left"""
        left = 0
        for chunk in iter(lambda: self.read(_CHUNK), b""):
            left += len(chunk)
        return left


def read_manifest(archive: zipfile.ZipFile, label: str) -> dict[str, Any] | None:
    """The manifest of ``archive`` (None if it has none), with its member list checked against the archive.

    :param archive: an open zip
    :param label: the file, for messages
    :return: the manifest
    """
    names = archive.namelist()
    duplicates = sorted({n for n in names if names.count(n) > 1})
    if duplicates:
        raise ValueError(f"{label}: the archive holds members more than once ({duplicates}); not a HIEROS save")
    if MANIFEST_NAME not in names:
        return None
    try:
        manifest = json.loads(archive.read(MANIFEST_NAME).decode())
    except (ValueError, UnicodeDecodeError, zipfile.BadZipFile, zlib.error) as err:
        raise ValueError(f"{label}: its {MANIFEST_NAME!r} is unreadable ({type(err).__name__}: {err})") from None
    sums = manifest.get("sha256") if isinstance(manifest, dict) else None
    if not isinstance(sums, dict):
        raise ValueError(f"{label}: its {MANIFEST_NAME!r} holds no 'sha256' table")
    missing = sorted(set(sums) - set(names))
    unlisted = sorted(set(names) - set(sums) - {MANIFEST_NAME})
    if missing or unlisted:
        raise ValueError(
            f"{label}: members changed after saving (missing: {missing}, not in the manifest: {unlisted}); the file "
            "was modified or corrupted"
        )
    return manifest


def check_digest(name: str, expected: Any, actual: str, label: str) -> None:
    """Raise ``ValueError`` naming member ``name`` unless its sha256 is the one the manifest records."""
    if actual != expected:
        raise ValueError(
            f"{label}: member {name!r} does not match the sha256 recorded when the file was saved (expected "
            f"{str(expected)[:16]}..., got {actual[:16]}...); the file was modified or corrupted after saving"
        )


def verify_archive(archive: zipfile.ZipFile, label: str) -> dict[str, Any] | None:
    """Check every member of ``archive`` against its manifest.

    :param archive: an open zip
    :param label: the file, for messages
    :return: the manifest, or None for an archive saved without one (SB3, or HIEROS before checksums)
    """
    manifest = read_manifest(archive, label)
    if manifest is not None:
        for name, expected in manifest["sha256"].items():
            check_digest(name, expected, _digest(archive, name, label), label)
    return manifest


# ------------------------------------------------------------------------------------------------ plain JSON values


def qualified_name(cls: type | None) -> str | None:
    """``module.qualname`` of a class (None stays None)."""
    return None if cls is None else f"{cls.__module__}.{cls.__qualname__}"


def schedule_to_json(schedule: Any, value_now: float) -> dict[str, Any]:
    """A plain JSON description of a learning rate (float or SB3 schedule) for loading without unpickling.

    SB3's ``ConstantSchedule`` and ``LinearSchedule`` (also inside ``FloatSchedule``) are described exactly; any
    other callable only by ``value_now``, the value it had when saved.

    :param schedule: the ``learning_rate`` attribute
    :param value_now: its value at the current progress
    :return: ``{"kind": "constant", "value": v}``, ``{"kind": "linear", "start", "end", "end_fraction"}`` or
        ``{"kind": "callable", "value": value_now}``
    """
    if isinstance(schedule, FloatSchedule):
        return schedule_to_json(schedule.value_schedule, value_now)
    if isinstance(schedule, int | float) and not isinstance(schedule, bool):
        return {"kind": "constant", "value": float(schedule)}
    if isinstance(schedule, ConstantSchedule):
        return {"kind": "constant", "value": float(schedule.val)}
    if isinstance(schedule, LinearSchedule):
        return {
            "kind": "linear",
            "start": float(schedule.start),
            "end": float(schedule.end),
            "end_fraction": float(schedule.end_fraction),
        }
    return {"kind": "callable", "value": float(value_now)}


def schedule_from_json(spec: Any) -> float | LinearSchedule:
    """The learning rate described by :func:`schedule_to_json` (a ``callable`` becomes its saved value, with a
    warning).

    :param spec: the description
    :return: a float or an SB3 ``LinearSchedule``
    """
    kind = spec.get("kind") if isinstance(spec, dict) else None
    numbers = {k: v for k, v in spec.items() if k != "kind"} if isinstance(spec, dict) else {}
    if not numbers or not all(isinstance(v, int | float) and math.isfinite(v) for v in numbers.values()):
        raise ValueError(f"learning-rate description {spec!r} in the manifest is not valid")
    if kind == "linear":
        return LinearSchedule(numbers["start"], numbers["end"], numbers["end_fraction"])
    if kind == "callable":
        warnings.warn(
            "the saved learning rate is a Python callable, which safe loading does not unpickle: it continues as the "
            f"constant {numbers['value']!r} it had when saved; pass custom_objects={{'learning_rate': ...}} to set it",
            stacklevel=4,
        )
    if kind not in ("constant", "callable"):
        raise ValueError(f"learning-rate description {spec!r} in the manifest has an unknown kind")
    return float(numbers["value"])


def _plain_episode_infos(infos: Any) -> list[dict[str, float]] | None:
    """Monitor episode infos as plain JSON (None when an entry is not a dict of finite numbers)."""
    out = []
    for info in infos:
        if not isinstance(info, Mapping):
            return None
        entry = {}
        for key, value in info.items():
            try:
                number = float(value)
            except (TypeError, ValueError):
                return None
            if not isinstance(key, str) or not math.isfinite(number):
                return None
            entry[key] = number
        out.append(entry)
    return out


def safe_load_values(model: Any) -> dict[str, Any]:
    """Plain JSON values of an SB3 off-policy model from which :func:`safe_load_objects` rebuilds its pickled entries.

    :param model: the model being saved
    :return: values for the manifest
    """
    return {
        "policy_class": qualified_name(model.policy_class),
        "replay_buffer_class": qualified_name(model.replay_buffer_class),
        "learning_rate": schedule_to_json(
            model.learning_rate, float(model.lr_schedule(model._current_progress_remaining))
        ),
        "ep_info_buffer": _plain_episode_infos(model.ep_info_buffer or []),
        "ep_success_buffer": [bool(s) for s in (model.ep_success_buffer or [])],
    }


# ------------------------------------------------------------------------------------------------ loading


def _space_mismatch(saved: Any, space: spaces.Space) -> str | None:
    """Why the plain JSON description of a saved space does not fit ``space`` (None if it fits)."""
    if not isinstance(saved, dict):
        return None  # a space saved as plain JSON cannot be compared; the parameter shapes still must match
    if saved.get(":type:") != str(type(space)):
        return f"saved {saved.get(':type:')}, got {type(space)}"
    if "_shape" in saved and saved["_shape"] is not None and list(saved["_shape"]) != list(space.shape or ()):
        return f"saved shape {tuple(saved['_shape'])}, got {space.shape}"
    if "dtype" in saved and space.dtype is not None and saved["dtype"] != str(space.dtype):
        return f"saved dtype {saved['dtype']}, got {space.dtype}"
    if isinstance(space, spaces.Discrete) and "n" in saved and saved["n"] != str(space.n):
        return f"saved n={saved['n']}, got n={space.n}"
    return None


def plain_builders(
    data: Mapping[str, Any], manifest: Mapping[str, Any] | None, classes: Mapping[str, Mapping[str, type]], label: str
) -> dict[str, Callable[[], Any]]:
    """Builders, which unpickle nothing, of the ``":serialized:"`` entries of a model's ``data`` that plain values
    (the manifest's and ``data``'s own) determine: everything SB3 pickles for HIEROS but the spaces.

    :param data: the ``data`` member as plain JSON
    :param manifest: the file's manifest (holds the policy class, learning rate and episode statistics)
    :param classes: per entry (``"policy_class"``, ``"replay_buffer_class"``), the classes a file may name there, by
        :func:`qualified_name`
    :param label: the file, for messages
    :return: entry -> zero-argument builder
    """
    values = dict(manifest or {})
    window = data.get("_stats_window_size", 100)
    window = window if isinstance(window, int) and not isinstance(window, bool) and window > 0 else 100

    def named_class(key: str) -> type:
        name = values.get(key)
        known_classes = classes.get(key, {})
        if name not in known_classes:
            known = ", ".join(sorted(known_classes))
            raise ValueError(
                f"{label}: safe loading cannot rebuild {key!r} (saved class {name!r}); it knows {known}. Pass "
                f"custom_objects={{{key!r}: <the class>}}, or load with safe=False if you trust the file"
            )
        return known_classes[name]

    def episode_infos() -> collections.deque:
        infos = values.get("ep_info_buffer") or []
        return collections.deque((dict(i) for i in infos if isinstance(i, dict)), maxlen=window)

    return {
        "policy_class": lambda: named_class("policy_class"),
        "replay_buffer_class": lambda: named_class("replay_buffer_class"),
        "learning_rate": lambda: schedule_from_json(values.get("learning_rate")),
        "lr_schedule": lambda: None,  # rebuilt from learning_rate by _setup_model
        "train_freq": lambda: TrainFreq(1, TrainFrequencyUnit.STEP),
        "_last_obs": lambda: None,  # the env is reset before training goes on
        "_last_original_obs": lambda: None,
        "_last_episode_starts": lambda: None,
        "ep_info_buffer": episode_infos,
        "ep_success_buffer": lambda: collections.deque(
            (bool(s) for s in values.get("ep_success_buffer") or []), maxlen=window
        ),
    }


def safe_load_objects(
    data: Mapping[str, Any],
    manifest: Mapping[str, Any] | None,
    observation_space: spaces.Space,
    action_space: spaces.Space,
    classes: Mapping[str, Mapping[str, type]],
    label: str,
    provided: Collection[str] = (),
) -> dict[str, Any]:
    """Replacements, built without unpickling, for every ``":serialized:"`` entry of a model's ``data``.

    :param data: the ``data`` member as plain JSON
    :param manifest: the file's manifest (holds the policy class, learning rate and episode statistics)
    :param observation_space: the environment's observation space (checked against the saved description)
    :param action_space: the environment's action space
    :param classes: as for :func:`plain_builders`
    :param label: the file, for messages
    :param provided: entries the caller replaces itself (``custom_objects``): nothing is built for them
    :return: ``custom_objects`` for SB3's ``load``
    """
    builders = plain_builders(data, manifest, classes, label)
    builders.update(observation_space=lambda: observation_space, action_space=lambda: action_space)
    for key, space in (("observation_space", observation_space), ("action_space", action_space)):
        if key in provided:
            continue
        why = _space_mismatch(data.get(key), space)
        if why is not None:
            raise ValueError(f"{label}: the env's {key.replace('_', ' ')} does not match the saved one ({why})")
    objects = {}
    for key, item in data.items():
        if not (isinstance(item, dict) and _SERIALIZED in item) or key in provided:
            continue
        if key not in builders:
            raise ValueError(
                f"{label}: entry {key!r} of its data is a pickled {item.get(':type:', 'object')}, which safe loading "
                f"does not unpickle; pass custom_objects={{{key!r}: ...}}, or safe=False if you trust the file"
            )
        objects[key] = builders[key]()
    return objects


def _unpickle(key: str, item: Mapping[str, Any], label: str) -> Any:
    """Unpickle one ``":serialized:"`` entry (runs the code it names: only for trusted files)."""
    try:
        return cloudpickle.loads(base64.b64decode(str(item[_SERIALIZED]).encode()))
    except Exception as err:  # any failure of arbitrary pickled content
        raise ValueError(
            f"{label}: entry {key!r} of its data could not be unpickled ({type(err).__name__}: {err}); pass "
            f"custom_objects={{{key!r}: ...}} to replace it"
        ) from None


def load_objects(
    data: Mapping[str, Any],
    custom_objects: Mapping[str, Any] | None,
    check_policy: Callable[[Any], None],
    label: str,
    fallbacks: Mapping[str, Callable[[], Any]] | None = None,
) -> dict[str, Any]:
    """Every ``":serialized:"`` entry of ``data`` unpickled exactly once (``custom_objects`` keys are not), the
    policy class first and checked by ``check_policy`` before anything else is unpickled.

    An entry that cannot be unpickled (e.g. a schedule pickled by another Python version) is rebuilt by its
    ``fallbacks`` builder with a warning, as SB3 warns and goes on; without one it raises ``ValueError``.

    :param data: the ``data`` member as plain JSON
    :param custom_objects: the user's replacements (win over the file)
    :param check_policy: raises ``ValueError`` for a policy class the caller cannot load
    :param label: the file, for messages
    :param fallbacks: builders from plain values (:func:`plain_builders`)
    :return: ``custom_objects`` for SB3's ``load``, so that SB3 unpickles nothing again
    """
    objects = dict(custom_objects or {})
    keys = [k for k, v in data.items() if isinstance(v, dict) and _SERIALIZED in v and k not in objects]
    keys.sort(key=lambda k: k != "policy_class")  # the policy class first: a foreign file is refused at once
    if "policy_class" not in keys:
        check_policy(objects.get("policy_class", data.get("policy_class")))
    for key in keys:
        try:
            objects[key] = _unpickle(key, data[key], label)
        except ValueError as err:
            if key not in (fallbacks or {}):
                raise
            warnings.warn(f"{err}; rebuilt from the file's plain values instead", stacklevel=4)
            objects[key] = fallbacks[key]()  # type: ignore[index]
        if key == "policy_class":
            check_policy(objects[key])
    return objects


def _open_zip(path: str | pathlib.Path | io.BufferedIOBase, suffix: str) -> tuple[BinaryIO, bool]:
    """``path`` opened for reading (``.<suffix>`` tried when the path does not exist), and whether to close it."""
    if isinstance(path, str | pathlib.Path):
        path = pathlib.Path(path)
        if not path.exists() and path.suffix == "" and pathlib.Path(f"{path}.{suffix}").exists():
            path = pathlib.Path(f"{path}.{suffix}")
        return path.open("rb"), True
    return path, False  # type: ignore[return-value]


def prepare_model_load(
    path: str | pathlib.Path | io.BufferedIOBase,
    custom_objects: Mapping[str, Any] | None,
    safe: bool,
    env_spaces: tuple[spaces.Space, spaces.Space] | None,
    policy_base: type,
    policies: Mapping[str, type],
    buffers: Mapping[str, type],
) -> tuple[dict[str, Any], dict[str, Any]]:
    """Check a model zip before SB3 loads it and resolve the pickled entries of its ``data`` once (or never).

    The zip must be readable, hold ``data``, match its manifest's checksums and name a subclass of ``policy_base``;
    otherwise ``ValueError`` is raised before any object is built. A file object is left at its position.

    :param path: what ``load`` was given
    :param custom_objects: the user's replacements
    :param safe: unpickle nothing (:func:`safe_load_objects`); ``env_spaces`` is then required
    :param env_spaces: the observation and action spaces of the env passed to ``load``
    :param policy_base: the policy class every loadable file names (a subclass of it)
    :param policies: policy classes a safe load may name, by :func:`qualified_name`
    :param buffers: replay-buffer classes a safe load may name
    :return: ``custom_objects`` for SB3's ``load`` (SB3 then unpickles nothing), and the ``data`` member as plain JSON
        (pickled entries left as they are in the file)
    """
    file, close = _open_zip(path, "zip")
    start = file.tell() if file.seekable() else None
    label = str(path)
    try:
        with zipfile.ZipFile(file) as archive:
            manifest = verify_archive(archive, label)
            names = archive.namelist()
            if "data" not in names:
                raise ValueError(
                    f"{label} is not a HIEROS save: none of its {len(names)} zip entries is 'data'; the file may be "
                    "truncated"
                )
            data = json.loads(archive.read("data").decode())
    except (zipfile.BadZipFile, zlib.error, EOFError, UnicodeDecodeError, json.JSONDecodeError, KeyError) as err:
        raise ValueError(
            f"{label} is not a readable HIEROS save (truncated or corrupted?): {type(err).__name__}: {err}"
        ) from None
    finally:
        if close:
            file.close()
        elif start is not None:
            file.seek(start)
    if not isinstance(data, dict):
        raise ValueError(f"{label} is not a HIEROS save: its 'data' entry is not a JSON object")

    def check_policy(policy_class: Any) -> None:
        if not (isinstance(policy_class, type) and issubclass(policy_class, policy_base)):
            name = getattr(policy_class, "__qualname__", repr(policy_class))
            raise ValueError(
                f"{label} was not saved by HIEROS: its policy class is {name}, expected a {policy_base.__name__}; "
                "load it with the algorithm that saved it"
            )

    classes = {"policy_class": policies, "replay_buffer_class": buffers}
    if not safe:
        objects = load_objects(
            data, custom_objects, check_policy, label, plain_builders(data, manifest, classes, label)
        )
        return objects, data
    saved_policy = data.get("policy_class")
    module = saved_policy.get("__module__") if isinstance(saved_policy, dict) else None
    if manifest is None and "policy_class" not in (custom_objects or {}):
        if not str(module).startswith(policy_base.__module__.split(".")[0]):
            raise ValueError(
                f"{label} was not saved by HIEROS: its policy class comes from module {module}, expected a "
                f"{policy_base.__name__}; load it with the algorithm that saved it"
            )
        raise ValueError(
            f"{label} has no {MANIFEST_NAME!r}: it was saved before HIEROS could load without unpickling. Load it "
            "once with safe=False (only if you trust it) and save it again, or pass custom_objects={'policy_class': "
            "...}"
        )
    assert env_spaces is not None
    objects = safe_load_objects(data, manifest, *env_spaces, classes, label, provided=set(custom_objects or {}))
    objects.update(custom_objects or {})
    check_policy(objects.get("policy_class"))
    return objects, data
