"""A GigE Vision camera on 127.0.0.1 that streams given images: Aravis's own fake GV camera (the device behind
``arv-fake-gv-camera-0.8``: GVCP control, GVSP streaming, ``gvsp-lost-ratio``) with its fill pattern replaced.

Run: ``python tests/gvsp_image_server.py SERIAL LOST_PER_MILLE STACK.npy INDEX_FILE``. Every triggered frame
is ``STACK[i]`` (uint8, H x W, Mono8) where ``i`` is the integer in INDEX_FILE when the frame is exposed: the
test's stand-in projector writes the index of the pattern it shows there, so a re-captured frame sees the
same pattern, as on a real cell.

Why ctypes: ``arv_fake_camera_set_fill_pattern`` keeps its callback beyond the call, which PyGObject cannot
express for this function (its closure is freed on return), and a fill pattern must write into the
ArvBuffer's memory, which the GObject binding only hands out as a copy.
"""

from __future__ import annotations

import ctypes
import sys
from pathlib import Path

import gi
import numpy as np

gi.require_version("Aravis", "0.8")
from gi.repository import Aravis, GLib  # noqa: E402

FILL = ctypes.CFUNCTYPE(
    None, ctypes.c_void_p, ctypes.c_void_p, ctypes.c_uint32, ctypes.c_uint32, ctypes.c_uint32
)


def _pointer(obj: object) -> int:
    get = ctypes.pythonapi.PyCapsule_GetPointer
    get.restype, get.argtypes = ctypes.c_void_p, [ctypes.py_object, ctypes.c_char_p]
    return get(obj.__gpointer__, None)  # type: ignore[attr-defined]


def main(serial: str, lost_per_mille: int, stack_path: Path, index_path: Path) -> None:
    stack = np.ascontiguousarray(np.load(stack_path), dtype=np.uint8)
    lib = ctypes.CDLL("libaravis-0.8.so.0")
    lib.arv_buffer_get_data.restype = ctypes.c_void_p
    lib.arv_buffer_get_data.argtypes = [ctypes.c_void_p, ctypes.POINTER(ctypes.c_size_t)]
    lib.arv_fake_camera_set_fill_pattern.argtypes = [ctypes.c_void_p, FILL, ctypes.c_void_p]

    def fill(buffer: int, _data: int, _exposure_us: int, _gain: int, _pixel_format: int) -> None:
        image = stack[int(index_path.read_text() or 0) % len(stack)]
        # the fake camera checked that the buffer holds its payload before calling; the received size is
        # only set afterwards, so the payload is the size to write (a mismatch leaves the frame unfilled)
        if fake.get_payload() != image.nbytes:
            print(f"payload {fake.get_payload()} B != image {image.shape}: not filled", file=sys.stderr)
            return
        target = lib.arv_buffer_get_data(buffer, ctypes.byref(ctypes.c_size_t()))
        ctypes.memmove(target, image.ctypes.data, image.nbytes)

    callback = FILL(fill)  # kept alive for the process's lifetime
    camera = Aravis.GvFakeCamera.new_full("127.0.0.1", serial, None)
    camera.set_property("gvsp-lost-ratio", lost_per_mille / 1000.0)
    if not camera.is_running():
        sys.exit(f"fake camera {serial} did not start on 127.0.0.1 (is another one on port 3956?)")
    fake = camera.get_fake_camera()
    lib.arv_fake_camera_set_fill_pattern(_pointer(fake), callback, None)
    print("ready", flush=True)
    GLib.MainLoop().run()


if __name__ == "__main__":
    main(sys.argv[1], int(sys.argv[2]), Path(sys.argv[3]), Path(sys.argv[4]))
