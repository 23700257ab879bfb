"""The layering of DESIGN.md section 2, checked on every module's imports, and module sizes.

Imports only point down ``heartreg -> registration -> modeling -> imaging ->
hrcore``; the phantom (``heartreg.phantom``) is the independent ground truth and
imports none of the packages it tests. Imports inside functions count too: a
lazy import is still a dependency.
"""

from __future__ import annotations

import ast
import importlib
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]

#: What each layer may import from the project (itself always allowed).
ALLOWED = {
    "hrcore": set(),
    "imaging": {"hrcore"},
    "modeling": {"hrcore", "imaging"},
    "registration": {"hrcore", "imaging", "modeling"},
    "heartreg": {"hrcore", "imaging", "modeling", "registration"},
}
PROJECT = set(ALLOWED)


def _project_imports(path: Path) -> set[str]:
    """Dotted names of the project modules that ``path`` imports."""
    names = set()
    for node in ast.walk(ast.parse(path.read_text(), filename=str(path))):
        if isinstance(node, ast.Import):
            names.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            names.add(node.module)
    return {n for n in names if n.split(".")[0] in PROJECT}


def _modules(package: str) -> list[Path]:
    return sorted((ROOT / package).rglob("*.py"))


@pytest.mark.parametrize("package", sorted(ALLOWED))
def test_imports_only_point_down(package):
    offenders = []
    for path in _modules(package):
        for name in _project_imports(path):
            top = name.split(".")[0]
            if top != package and top not in ALLOWED[package]:
                offenders.append(f"{path.relative_to(ROOT)} imports {name}")
    assert not offenders, "imports pointing up the stack:\n" + "\n".join(offenders)


def test_phantom_is_independent_of_the_packages_it_tests():
    offenders = []
    for path in _modules("heartreg/phantom"):
        for name in _project_imports(path):
            if name.split(".")[0] in {"imaging", "modeling", "registration"}:
                offenders.append(f"{path.relative_to(ROOT)} imports {name}")
            elif name.startswith("heartreg") and not name.startswith("heartreg.phantom") and name != "heartreg":
                offenders.append(f"{path.relative_to(ROOT)} imports {name}")
    assert not offenders, "the phantom imports what it must test:\n" + "\n".join(offenders)


def test_every_domain_error_derives_from_heartregerror():
    from hrcore.errors import HeartregError

    outside = []
    for package in ("imaging", "modeling", "registration", "heartreg"):
        for path in _modules(package):
            if path.name == "__main__.py":  # runs the command line when imported
                continue
            module = importlib.import_module(".".join(path.relative_to(ROOT).with_suffix("").parts))
            for name, value in vars(module).items():
                if (
                    isinstance(value, type)
                    and issubclass(value, Exception)
                    and name.endswith("Error")
                    and value.__module__ == module.__name__
                    and not issubclass(value, HeartregError)
                ):
                    outside.append(f"{module.__name__}.{name}")
    assert not outside, "errors outside the HeartregError family: " + ", ".join(outside)


#: Issue 11: modules of one concept each, "under ~500 lines".
MAX_MODULE_LINES = 500


def test_every_module_stays_under_the_size_limit():
    long = []
    for package in sorted(ALLOWED):
        for path in _modules(package):
            n = len(path.read_text(encoding="utf-8").splitlines())
            if n > MAX_MODULE_LINES:
                long.append(f"{path.relative_to(ROOT)}: {n} lines")
    assert not long, f"modules over {MAX_MODULE_LINES} lines (split by concept):\n" + "\n".join(long)
