"""Import Open3D, first making its libusb dependency loadable when the system lacks it.

Open3D's wheels (``open3d`` and ``open3d-cpu`` alike) link against ``libusb-1.0.so.0`` for camera
support railtraj never uses. Debian's ``libusb-1.0-0`` provides it; where it is absent we preload
the copy shipped by the ``libusb-package`` wheel so that ``pip install`` alone is enough.
Import Open3D as ``from railtraj.o3d import o3d`` everywhere.
"""

from __future__ import annotations

import ctypes
import ctypes.util

from railtraj.errors import RailtrajError


def _preload_libusb() -> None:
    if ctypes.util.find_library("usb-1.0"):
        return
    try:
        import libusb_package
    except ImportError:
        return
    path = libusb_package.get_library_path()
    if path is not None:
        ctypes.CDLL(str(path), mode=ctypes.RTLD_GLOBAL)


_preload_libusb()
try:
    import open3d as o3d  # noqa: E402
except ImportError as exc:  # pragma: no cover - depends on the machine
    raise RailtrajError(f"Open3D cannot be imported ({exc}); install Debian's libusb-1.0-0, libgl1 and "
                        "libegl1, or `pip install libusb-package`") from exc

__all__ = ["o3d"]
