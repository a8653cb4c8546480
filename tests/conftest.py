"""Shared pytest fixtures."""

from __future__ import annotations

from collections.abc import Iterator

import pytest
import torch as th


@pytest.fixture(autouse=True)
def _one_thread() -> Iterator[None]:
    """Run every test on one torch thread: the tiny models gain nothing from more, and CI has 2 cores."""
    threads = th.get_num_threads()
    th.set_num_threads(1)
    yield
    th.set_num_threads(threads)
