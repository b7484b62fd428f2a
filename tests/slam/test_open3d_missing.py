"""Open3D (the `bench` extra) missing or installed but unloadable: the error says what to install. On a fresh
Debian machine the wheel imports but its library cannot load (`libusb-1.0.so.0` missing): that names the system
package, not `pip install open3d-cpu` (which is already done)."""
from __future__ import annotations

import builtins
import sys

import pytest

from trisplat.slam import open3d_baseline


def _failing_import(monkeypatch, exc):
    real = builtins.__import__

    def fake(name, *args, **kwargs):
        if name == "open3d" or name.startswith("open3d."):
            raise exc
        return real(name, *args, **kwargs)

    monkeypatch.delitem(sys.modules, "open3d", raising=False)
    monkeypatch.setattr(builtins, "__import__", fake)


@pytest.mark.parametrize("exc", [
    ImportError("libusb-1.0.so.0: cannot open shared object file: No such file or directory"),
    OSError("libusb-1.0.so.0: cannot open shared object file: No such file or directory"),
], ids=["ImportError", "OSError"])
def test_open3d_without_libusb_names_the_system_package(monkeypatch, exc):
    _failing_import(monkeypatch, exc)
    with pytest.raises(ImportError) as info:
        open3d_baseline._o3d()
    msg = str(info.value)
    assert "apt install libusb-1.0-0" in msg and "libusb-1.0.so.0: cannot open shared object file" in msg
    assert "pip install open3d-cpu" not in msg


def test_open3d_with_another_missing_library_names_it(monkeypatch):
    _failing_import(monkeypatch, ImportError("libfoo.so.3: cannot open shared object file"))
    with pytest.raises(ImportError, match=r"open3d is installed but cannot load: libfoo\.so\.3"):
        open3d_baseline._o3d()


def test_open3d_not_installed_names_the_pip_package(monkeypatch):
    monkeypatch.setitem(sys.modules, "open3d", None)  # `import open3d` raises ModuleNotFoundError
    with pytest.raises(ImportError, match=r"pip install open3d-cpu==0\.20\.0"):
        open3d_baseline._o3d()
