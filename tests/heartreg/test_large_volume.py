"""A CT too large for the memory is refused in one line before its pixels are read.

Linux overcommits: the volume's ``np.empty`` succeeds whatever its size, and a
1024 x 1024 x 2000 study (4 GB as int16, ~12 GB at ``heartreg model``'s peak)
was read for minutes before the process was killed without a word, or failed
inside the segmentation with an unrelated hint (``--step``, ``--faces``).  The
memory available is set here (the sample study is 2.4 MB as int16) rather than
filled: a real refusal would need the machine's memory.
"""

from __future__ import annotations

import importlib
from pathlib import Path

import pytest

import hrcore.memory
from heartreg import cli
from imaging.series import load_study
from imaging.volume import SeriesError
from modeling.options import MODEL_MEMORY_FACTOR

SAMPLE = Path(__file__).resolve().parents[2] / "sample_dicom" / "ct"
INT16_BYTES = 128 * 128 * 72 * 2  # the sample study's volume
series_module = importlib.import_module("imaging.series")  # not ``imaging.series``: the package exports a name so


@pytest.fixture
def memory(monkeypatch):
    """Set the memory the process is told is available; fail if a pixel is read."""
    reads = []
    real_assemble = series_module._assemble

    def counting_assemble(plan, **kw):
        reads.append(plan.n_out)
        return real_assemble(plan, **kw)

    monkeypatch.setattr(series_module, "_assemble", counting_assemble)

    def set_available(n_bytes):
        monkeypatch.setattr(hrcore.memory, "available_memory_bytes", lambda: n_bytes)
        return reads

    return set_available


def test_a_series_needing_more_than_the_memory_is_refused_before_its_pixels(memory):
    reads = memory(2 * INT16_BYTES)
    with pytest.raises(SeriesError) as info:
        load_study(SAMPLE, memory_factor=MODEL_MEMORY_FACTOR)
    message = str(info.value)
    assert reads == []  # refused from the headers: no slice read
    assert "\n" not in message
    assert "128 x 128 x 72 voxels need about 0.00659 GB of memory (3x its 0.0022 GB as int16)" in message
    assert "0.00439 GB is available" in message
    assert load_study(SAMPLE).hu.nbytes == INT16_BYTES  # the volume alone (phases) fits: read
    assert reads == [72]


def test_unknown_memory_refuses_nothing(memory):
    reads = memory(None)  # not Linux
    assert load_study(SAMPLE, memory_factor=MODEL_MEMORY_FACTOR).hu.shape == (72, 128, 128)
    assert reads == [72]


def test_the_model_command_refuses_a_too_large_ct_in_one_line(memory, tmp_path, capsys):
    reads = memory(MODEL_MEMORY_FACTOR * INT16_BYTES - 1)
    out = tmp_path / "model"
    assert cli.main(["model", str(SAMPLE), "-o", str(out), "-q"]) == 1
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith("heartreg model: error: series [0] ")
    assert "give a reconstruction with fewer voxels" in err
    assert reads == [] and not out.exists()


@pytest.mark.parametrize("kind", ["nii.gz", "nrrd", "4d.nii.gz"])
def test_a_volume_file_too_large_is_refused_from_its_header(memory, tmp_path, capsys, kind, monkeypatch):
    """A NIfTI or NRRD CT needing more than the memory is refused as a DICOM series is, from its header before
    its voxels are read (an audit: volume files were read whole whatever their size)."""
    import numpy as np

    import imaging.volume_file as volume_file

    memory(MODEL_MEMORY_FACTOR * 2 * 40 * 30 * 20 - 1)
    data = np.full((40, 30, 20), -1000, np.int16)  # i, j, k
    path = tmp_path / f"ct.{kind}"
    if kind == "nrrd":
        header = ("NRRD0004\ntype: short\ndimension: 3\nspace: left-posterior-superior\nsizes: 40 30 20\n"
                  "space directions: (1,0,0) (0,1,0) (0,0,2)\nkinds: domain domain domain\nendian: little\n"
                  "encoding: raw\nspace origin: (0,0,0)\n\n")
        path.write_bytes(header.encode() + data.transpose(2, 1, 0).tobytes())
    else:
        import nibabel as nib

        # x, y, z, 1 (one time point) is read as the 3-D volume: its size is that of its first three axes
        nib.save(nib.Nifti1Image(data[..., None] if kind.startswith("4d") else data, np.diag([1.0, 1.0, 2.0, 1.0])),
                 str(path))
    read = []
    monkeypatch.setattr(volume_file, "read_nifti_volume", lambda p: read.append(p))
    monkeypatch.setattr(volume_file, "read_nrrd_volume", lambda p: read.append(p))
    assert cli.main(["model", str(path), "-o", str(tmp_path / "model"), "-q"]) == 1
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "40 x 30 x 20 voxels need about" in err and "GB is available" in err, err
    assert read == [] and not (tmp_path / "model").exists()
