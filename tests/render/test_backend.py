"""Open3D's import: a missing system library or package is a PoseflowError that says what to do."""

from __future__ import annotations

import types

import numpy as np
import pytest

from poseflow.cli import main
from poseflow.errors import MissingDependencyError, MissingSystemLibraryError, PoseflowError
from poseflow.render import Renderer, backend
from poseflow.render.mesh import TexturedMesh


def _failing_import(exc):
    def import_module(name, package=None):
        if name == "open3d":
            raise exc
        raise AssertionError(f"unexpected import of {name}")

    return types.SimpleNamespace(import_module=import_module)


@pytest.mark.parametrize(
    ("message", "library", "apt"),
    [
        ("libGL.so.1: cannot open shared object file: No such file or directory", "libGL.so.1",
         "libgl1"),
        ("libEGL.so.1: cannot open shared object file: No such file or directory", "libEGL.so.1",
         "libegl1"),
        ("libusb-1.0.so.0: cannot open shared object file", "libusb-1.0.so.0", "libusb-1.0-0"),
        ("libgomp.so.1: cannot open shared object file", "libgomp.so.1", "libgomp1"),
    ],
)  # fmt: skip
def test_a_missing_system_library_names_its_apt_package(monkeypatch, message, library, apt):
    for exc_type in (OSError, ImportError):
        monkeypatch.setattr(backend, "importlib", _failing_import(exc_type(message)))
        with pytest.raises(MissingSystemLibraryError) as info:
            backend.import_open3d("rendering")
        assert isinstance(info.value, ImportError) and isinstance(info.value, PoseflowError)
        assert library in str(info.value) and f"apt-get install {apt}" in str(info.value)


def test_open3d_not_installed_says_how_to_install_it(monkeypatch):
    exc = ModuleNotFoundError("No module named 'open3d'", name="open3d")
    monkeypatch.setattr(backend, "importlib", _failing_import(exc))
    with pytest.raises(MissingDependencyError, match="pip install open3d"):
        backend.import_open3d()


def test_an_unrelated_import_error_is_not_disguised(monkeypatch):
    monkeypatch.setattr(backend, "importlib", _failing_import(ImportError("circular import")))
    with pytest.raises(ImportError, match="circular import") as info:
        backend.import_open3d()
    assert not isinstance(info.value, PoseflowError)


def test_the_renderer_and_synth_report_the_package(monkeypatch, tmp_path, capsys):
    message = "libGL.so.1: cannot open shared object file: No such file or directory"
    monkeypatch.setattr(backend, "importlib", _failing_import(OSError(message)))
    mesh = TexturedMesh(np.eye(3), np.array([[0, 1, 2]]))
    with pytest.raises(MissingSystemLibraryError, match="libgl1"):
        Renderer([mesh])
    argv = ["synth", str(tmp_path / "ds"), "--train", "0", "--test", "1", "--width", "32"]
    assert main([*argv, "--height", "24", "--no-progress"]) == 1
    assert "sudo apt-get install libgl1" in capsys.readouterr().err
