"""Every Python example of README.md and of the documentation pages runs.

The ``python`` code blocks of one page run in order in one namespace (a page reads like one session), in a temporary
working directory, with two changes that keep them cheap and leave their calls as written:

* budgets written with thousands separators (``10_000``, ``100_000``) are divided by 200 (at most 200);
* every ``HIEROS(...)`` gets the tiny run of the tests (``hieros_helpers.tiny_kwargs``: small preset, tiny networks,
  20 random steps, a short replay); the example's own ``config_overrides``, ``n_levels`` and other keywords are kept.
"""

from __future__ import annotations

import pathlib
import re
from typing import Any

import pytest
from hieros_helpers import tiny_kwargs

from sb3_hieros import HIEROS

ROOT = pathlib.Path(__file__).resolve().parents[1]
PAGES = sorted(
    [ROOT / "README.md", *(p for p in (ROOT / "docs").rglob("*.md") if "_build" not in p.parts)],
    key=lambda p: str(p),
)
BLOCK = re.compile(r"^```python\n(.*?)^```", re.DOTALL | re.MULTILINE)
BUDGET = re.compile(r"\b\d{1,3}(?:_\d{3})+\b")
#: Keywords that size a run; the examples' values are replaced by the tiny ones.
SIZING = {"preset", "buffer_size", "learning_starts", "batch_size", "batch_length", "train_ratio", "imag_horizon"}


def python_blocks(page: pathlib.Path) -> list[str]:
    """The ``python`` code blocks of a markdown page, in order."""
    return BLOCK.findall(page.read_text())


def scaled(source: str) -> str:
    """The source with every ``1_000``-style literal divided by 200 (at most 200)."""
    return BUDGET.sub(lambda m: str(min(200, int(m.group().replace("_", "")) // 200)), source)


def _merged(base: dict[str, Any], changes: dict[str, Any]) -> dict[str, Any]:
    merged = dict(base)
    for key, value in changes.items():
        merged[key] = _merged(merged[key], value) if isinstance(value, dict) and key in merged else value
    return merged


@pytest.fixture
def tiny_hieros(monkeypatch):
    original = HIEROS.__init__

    def tiny_init(self, policy, env, *args, **kwargs):
        if args or not kwargs.get("_init_setup_model", True):  # HIEROS.load builds the model itself
            return original(self, policy, env, *args, **kwargs)
        tiny = tiny_kwargs()
        overrides = _merged(tiny["config_overrides"], kwargs.pop("config_overrides", None) or {})
        given = {key: value for key, value in kwargs.items() if key not in SIZING}
        return original(self, policy, env, **{**tiny, **given, "config_overrides": overrides})

    monkeypatch.setattr(HIEROS, "__init__", tiny_init)


def test_the_pages_have_examples():
    counts = {page.relative_to(ROOT).as_posix(): len(python_blocks(page)) for page in PAGES}
    assert counts["README.md"] >= 4, counts
    assert counts["docs/getting_started.md"] >= 3, counts
    assert scaled("model.learn(10_000); x = 100_000; y = 1_000_000; z = 64") == (
        "model.learn(50); x = 200; y = 200; z = 64"
    )


@pytest.mark.filterwarnings("error:.*before the first update:UserWarning")  # every example trains
@pytest.mark.parametrize("page", [p for p in PAGES if python_blocks(p)], ids=lambda p: p.relative_to(ROOT).as_posix())
def test_examples_run(page, tiny_hieros, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    monkeypatch.setenv("MUJOCO_GL", "egl")
    namespace: dict[str, Any] = {"__name__": "__example__"}
    for index, block in enumerate(python_blocks(page)):
        code = compile(scaled(block), f"{page.name}[block {index}]", "exec")
        exec(code, namespace)  # the documentation's own examples
    trained = [value for value in namespace.values() if isinstance(value, HIEROS) and value.num_timesteps > 0]
    if "learn(" in page.read_text():
        assert trained, f"{page.name}: its examples call learn, but no trained model is left"
