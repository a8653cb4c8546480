"""Reading a HIEROS save before SB3 builds anything from it."""

from __future__ import annotations

import io
import pathlib
import zipfile
import zlib
from typing import Any

from stable_baselines3.common.save_util import json_to_data, open_path

from sb3_hieros.policies import HierosPolicy

__all__ = ["check_hieros_save"]


def check_hieros_save(path: str | pathlib.Path | io.BufferedIOBase, custom_objects: dict[str, Any] | None) -> None:
    """Raise ``ValueError`` unless ``path`` is a readable zip whose ``data`` entry names a :class:`HierosPolicy`.

    Reads only the small ``data`` entry (no tensors); a file-like ``path`` is left at its position.

    :param path: what :meth:`HIEROS.load` was given
    :param custom_objects: as for ``load``
    """
    file = open_path(path, "r", verbose=0, suffix="zip")
    start = file.tell() if file.seekable() else None
    n_entries, data = 0, None
    try:
        with zipfile.ZipFile(file) as archive:
            names = archive.namelist()
            n_entries = len(names)
            if "data" in names:
                data = json_to_data(archive.read("data").decode(), custom_objects=custom_objects)
    except (zipfile.BadZipFile, zlib.error, EOFError, UnicodeDecodeError, ValueError, KeyError) as err:
        raise ValueError(
            f"{path} is not a readable HIEROS save (truncated or corrupted?): {type(err).__name__}: {err}"
        ) from None
    finally:
        if isinstance(path, str | pathlib.Path):
            file.close()
        elif start is not None:
            file.seek(start)
    if data is None:
        raise ValueError(
            f"{path} is not a HIEROS save: none of its {n_entries} zip entries is 'data'; the file may be truncated"
        )
    policy_class = data.get("policy_class")
    if not (isinstance(policy_class, type) and issubclass(policy_class, HierosPolicy)):
        name = getattr(policy_class, "__qualname__", repr(policy_class))
        raise ValueError(
            f"{path} was not saved by HIEROS: its policy class is {name}, expected a HierosPolicy; load it with the "
            "algorithm that saved it"
        )
