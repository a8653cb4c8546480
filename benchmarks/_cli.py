"""Command-line helpers shared by the benchmark scripts."""

from __future__ import annotations

import argparse
import json
from typing import Any


def json_object(text: str) -> dict[str, Any]:
    """argparse type of the keyword options (``--config-overrides``, ``--policy-kwargs``, ...): a JSON object,
    refused with the text otherwise.

    :param text: the option's value
    :return: the object as a dict
    """
    try:
        value = json.loads(text)
    except json.JSONDecodeError as error:
        raise argparse.ArgumentTypeError(f"{text!r} is not JSON ({error}); expected a JSON object") from None
    if not isinstance(value, dict):
        raise argparse.ArgumentTypeError(f"{text!r} is a JSON {type(value).__name__}; expected a JSON object")
    return value
