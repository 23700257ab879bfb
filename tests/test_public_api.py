"""The public API of each package: what ``__all__`` holds, as docs/CONTRACTS.md
lists it, and the Examples section of every public function, run as doctests.

Examples read the repository's ``sample_dicom`` study by its relative path, as a
reader would from the checkout, so they run from the repository's root.
"""

from __future__ import annotations

import doctest
import importlib
import inspect
import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("hrcore", "imaging", "modeling", "registration")
#: Modules whose docstrings carry further examples (module level, helpers).
EXTRA_MODULES = ("hrcore.errors", "hrcore.geometry", "hrcore.options", "hrcore.output", "modeling.options",
                 "registration.localise", "registration.online", "registration.options", "registration.phase_estimate")


def _public_functions(package: str):
    module = importlib.import_module(package)
    return [(name, getattr(module, name)) for name in module.__all__ if inspect.isfunction(getattr(module, name))]


def _example_modules() -> list[str]:
    names = set(EXTRA_MODULES)
    for package in PACKAGES:
        names.update(func.__module__ for _, func in _public_functions(package))
    return sorted(names)


@pytest.mark.parametrize("package", PACKAGES)
def test_contracts_list_the_public_names(package):
    text = (ROOT / "docs" / "CONTRACTS.md").read_text(encoding="utf-8")
    section = text[text.index("## Public API"):]
    item = re.search(rf"^- `{package}`: (.*?)(?=^- |^#)", section, re.S | re.M).group(1)
    listed = set(re.findall(r"`(\w+)`", item))
    assert listed == set(importlib.import_module(package).__all__)


@pytest.mark.parametrize("package", PACKAGES)
def test_every_public_function_has_examples(package):
    missing = [name for name, func in _public_functions(package) if "Examples\n" not in (func.__doc__ or "")]
    assert not missing, f"{package}: no Examples section in {missing}"


@pytest.mark.parametrize("name", _example_modules())
def test_examples_run(name, monkeypatch):
    monkeypatch.chdir(ROOT)
    result = doctest.testmod(importlib.import_module(name), optionflags=doctest.ELLIPSIS | doctest.NORMALIZE_WHITESPACE)
    assert result.failed == 0
