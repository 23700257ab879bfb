"""hrcore.lazy: a package's names imported on first use, so a command imports what it runs."""

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from hrcore.lazy import lazy_exports

ROOT = Path(__file__).resolve().parents[2]


def test_lazy_exports_import_on_first_use_and_keep_the_name(monkeypatch):
    import types

    package = types.ModuleType("lazy_demo")
    monkeypatch.setitem(sys.modules, "lazy_demo", package)
    package.__getattr__, package.__dir__ = lazy_exports("lazy_demo", {"json.decoder": ("JSONDecodeError",)})
    assert "JSONDecodeError" in dir(package)
    assert "JSONDecodeError" not in vars(package)
    assert package.JSONDecodeError is json.JSONDecodeError
    assert vars(package)["JSONDecodeError"] is json.JSONDecodeError  # kept: the next access is a plain lookup
    with pytest.raises(AttributeError, match="no attribute 'nothing'"):
        package.nothing  # noqa: B018


def test_packages_give_every_public_name():
    import heartreg.phantom
    import registration

    import imaging

    for package in (heartreg.phantom, registration, imaging):
        assert all(getattr(package, name) is not None for name in package.__all__)


def test_model_command_imports_neither_phantom_nor_registration():
    """The parser reads the phantom's presets and the registration's defaults: their modules alone; nor
    do the model's modules import the ECG filters' scipy.signal (with scipy.stats, ~0.6 s) or trimesh
    (~0.25 s), which a model from a study's R-peak stamps does not use.
    """
    code = (
        "import sys\n"
        "ALLOWED = ('heartreg.phantom.config', 'registration.options', 'registration.motion_model')\n"
        "from heartreg.cli_parser import _build_parser\n"
        "_build_parser()\n"
        "import modeling, imaging, imaging.phase, modeling.build, modeling.ct_overlay, heartreg.pipeline\n"
        "print(sorted(m for m in sys.modules if m.startswith(('heartreg.phantom.', 'registration.', "
        "'scipy.signal', 'trimesh')) and m not in ALLOWED))\n"
    )
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, cwd=ROOT, check=True)
    assert out.stdout.strip() == "[]", out.stdout
