"""Pixel-exact pattern display: a borderless full-screen SDL2 window on one monitor (the projector's HDMI).

Pixel exactness is enforced, not hoped for: the streaming texture has exactly the size of the display mode,
the renderer's output must have that size too (so the copy is 1:1; a high-DPI or scaled desktop is refused),
filtering is nearest, and SDL applies no colour management. A grey image is uploaded as ARGB8888 with R=G=B.

SDL is used from one thread only (the display thread): it creates the window, then takes frames from a queue,
uploads, optionally reads the back buffer back (``readback``: the pixels the GPU will scan out, before the
flip), presents with vsync and resolves the caller's future. :meth:`HdmiDisplay.show` returns once its frame
is presented, or raises DeviceTimeout. ``present_count`` and ``last_present_s`` (time.monotonic) let the
caller time a software-delay trigger (docs/hardware.md).

pysdl2 and pysdl2-dll (SDL2 binaries) come from PyPI and are imported lazily, in the display thread. For tests
and headless machines, ``video_driver: offscreen`` (or ``dummy``) with ``renderer: software`` needs no X
server or GPU.
"""

from __future__ import annotations

import ctypes
import queue
import threading
import time
import warnings
from concurrent.futures import Future
from concurrent.futures import TimeoutError as FutureTimeout
from typing import Annotated, Any

import numpy as np
from numpy.typing import NDArray
from pydantic import Field

from cell.config import Strict
from cell.errors import DeviceFault, DeviceProtocolError, DeviceTimeout

# SDL keeps one video subsystem per process and wants it used from one thread: one display at a time.
_SDL_OWNER = threading.Lock()


class HdmiDisplayOptions(Strict):
    """Where and how to show patterns; ``sensor.projector.options.display`` for a serial projector."""

    display: Annotated[int, Field(ge=0, le=15)] = Field(0, description="monitor index as SDL numbers them")
    mode: tuple[int, int] | None = Field(
        None, description="(width, height) of an exclusive full-screen mode; None: the desktop's current mode"
    )
    refresh_hz: Annotated[float, Field(gt=0, le=1000)] | None = Field(
        None, description="refresh rate of the exclusive mode (needs mode); None: the highest offered"
    )
    video_driver: str | None = Field(
        None, description="SDL video driver (x11, wayland, kmsdrm; offscreen, dummy: tests); None: default"
    )
    renderer: str | None = Field(
        None, description="SDL render driver (opengl, opengles2, software); None: SDL's choice"
    )
    vsync: bool = Field(True, description="present on the vertical blank (HdmiDisplay.vsync says if granted)")
    readback: bool = Field(True, description="read every frame back from the back buffer (current_image)")
    present_timeout_s: Annotated[float, Field(gt=0, le=60)] = 1.0
    open_timeout_s: Annotated[float, Field(gt=0, le=60)] = 5.0


def _import_sdl() -> Any:
    """pysdl2 with its bundled SDL2 binaries (pysdl2-dll); a clear DeviceFault if missing."""
    try:
        with warnings.catch_warnings():  # pysdl2 warns that it uses the pysdl2-dll binaries: that is the plan
            warnings.simplefilter("ignore", UserWarning)
            import sdl2
    except ImportError as exc:
        raise ImportError(f"{exc}; pip install pysdl2 pysdl2-dll") from exc
    return sdl2


class _SdlError(Exception):
    pass


class HdmiDisplay:
    """A full-screen pattern window presenting (H, W) uint8 images 1:1 from its own thread."""

    def __init__(self, options: HdmiDisplayOptions | None = None, *, name: str = "display") -> None:
        self.name = name
        self.options = options or HdmiDisplayOptions()
        self._queue: queue.Queue[tuple[NDArray[np.uint8], Future[float]] | None] = queue.Queue()
        self._thread: threading.Thread | None = None
        self._size: tuple[int, int] | None = None
        self._refresh_hz = 0.0
        self._vsync = False
        self._renderer_name = ""
        self._rgb: NDArray[np.uint8] | None = None
        self.present_count = 0
        self.last_present_s = float("nan")

    # ----------------------------------------------------------------------------------------- caller side
    @property
    def is_open(self) -> bool:
        return self._thread is not None and self._thread.is_alive()

    @property
    def size(self) -> tuple[int, int]:
        """(width, height) of the display mode, px; the only image size :meth:`show` accepts."""
        if self._size is None:
            raise DeviceFault(self.name, "display not open; call open() first")
        return self._size

    @property
    def refresh_hz(self) -> float:
        """Refresh rate the display mode reports (0 if the driver does not say)."""
        return self._refresh_hz

    @property
    def vsync(self) -> bool:
        """True when the renderer presents on the vertical blank."""
        return self._vsync

    @property
    def renderer_name(self) -> str:
        return self._renderer_name

    def open(self) -> None:
        """Start the display thread, which opens the window; idempotent. DeviceFault if SDL cannot."""
        if self.is_open:
            return
        if not _SDL_OWNER.acquire(blocking=False):
            raise DeviceFault(self.name, "another HdmiDisplay is open in this process; SDL allows one")
        opened: Future[None] = Future()
        self._thread = threading.Thread(
            target=self._run, args=(opened,), name=f"{self.name}-sdl", daemon=True
        )
        self._thread.start()
        try:
            opened.result(timeout=self.options.open_timeout_s)
        except FutureTimeout:  # the thread is left to finish; close() joins it and frees SDL
            self._queue.put(None)
            raise DeviceTimeout(
                self.name, f"window not open within {self.options.open_timeout_s:g} s"
            ) from None
        except Exception as exc:
            self._thread.join(timeout=self.options.open_timeout_s)
            self._thread = None
            _SDL_OWNER.release()
            if isinstance(exc, DeviceFault):
                raise
            raise DeviceFault(self.name, f"cannot open the pattern display: {exc}") from exc

    def close(self) -> None:
        """Stop the thread and destroy the window; idempotent."""
        if self._thread is None:
            return
        self._queue.put(None)
        self._thread.join(timeout=self.options.open_timeout_s)
        self._thread = None
        self._rgb = None
        _SDL_OWNER.release()

    def show(self, image: NDArray[np.uint8]) -> float:
        """Present ``image`` (H, W) uint8 1:1; returns the time.monotonic() of the present once it is done."""
        if not self.is_open:
            raise DeviceFault(self.name, "display not open; call open() first")
        w, h = self.size
        img = np.asarray(image)
        if img.dtype != np.uint8 or img.shape != (h, w):
            raise DeviceProtocolError(
                self.name,
                f"image must be uint8 of shape ({h}, {w}) (the display mode), got {img.dtype} {img.shape}",
            )
        done: Future[float] = Future()
        self._queue.put((img.copy(), done))
        try:
            return done.result(timeout=self.options.present_timeout_s)
        except FutureTimeout:
            done.cancel()
            raise DeviceTimeout(
                self.name, f"frame not presented within {self.options.present_timeout_s:g} s"
            ) from None
        except _SdlError as exc:
            raise DeviceFault(self.name, f"present failed: {exc}") from exc

    @property
    def current_rgb(self) -> NDArray[np.uint8]:
        """(H, W, 3) RGB read back from the last presented frame (needs ``readback``)."""
        if not self.options.readback:
            raise AttributeError(f"{self.name}: readback is off (options.readback)")
        if self._rgb is None:
            raise DeviceFault(self.name, "nothing presented yet")
        return self._rgb

    @property
    def current_image(self) -> NDArray[np.uint8]:
        """The last presented frame as (H, W) uint8; DeviceProtocolError if its channels differ."""
        rgb = self.current_rgb
        grey = rgb[:, :, 0]
        if not (np.array_equal(grey, rgb[:, :, 1]) and np.array_equal(grey, rgb[:, :, 2])):
            raise DeviceProtocolError(self.name, "read-back channels differ: something alters colours")
        return grey

    # ----------------------------------------------------------------------------------------- SDL thread
    def _run(self, opened: Future[None]) -> None:
        try:
            sdl = _import_sdl()
        except ImportError as exc:
            opened.set_exception(DeviceFault(self.name, f"pysdl2 is not installed: {exc}"))
            return
        handles: dict[str, Any] = {}
        try:
            self._open_window(sdl, handles)
        except Exception as exc:  # every SDL failure surfaces in open() as a DeviceFault
            self._teardown(sdl, handles)
            opened.set_exception(exc)
            return
        opened.set_result(None)
        try:
            while True:
                try:
                    item = self._queue.get(timeout=0.05)
                except queue.Empty:
                    sdl.SDL_PumpEvents()  # keep the window responsive to the window manager
                    continue
                if item is None:
                    break
                image, done = item
                if not done.set_running_or_notify_cancel():
                    continue
                try:
                    done.set_result(self._present(sdl, handles, image))
                except Exception as exc:
                    done.set_exception(_SdlError(str(exc)))
        finally:
            self._teardown(sdl, handles)

    def _fail(self, sdl: Any, what: str) -> DeviceFault:
        return DeviceFault(self.name, f"{what}: {sdl.SDL_GetError().decode(errors='replace')}")

    def _open_window(self, sdl: Any, h: dict[str, Any]) -> None:
        o = self.options
        sdl.SDL_SetHint(sdl.SDL_HINT_RENDER_SCALE_QUALITY, b"0")  # nearest, should anything ever scale
        sdl.SDL_SetHint(sdl.SDL_HINT_VIDEO_MINIMIZE_ON_FOCUS_LOSS, b"0")  # stay up when the operator clicks
        if o.video_driver:
            sdl.SDL_SetHint(sdl.SDL_HINT_VIDEODRIVER, o.video_driver.encode())
        if sdl.SDL_InitSubSystem(sdl.SDL_INIT_VIDEO) != 0:
            raise self._fail(sdl, f"SDL video init (driver {o.video_driver or 'default'})")
        h["video"] = True
        n = sdl.SDL_GetNumVideoDisplays()
        if o.display >= n:
            raise DeviceFault(
                self.name, f"display {o.display} requested but SDL sees {n} display(s) (0..{n - 1})"
            )
        mode = sdl.SDL_DisplayMode()
        flags = sdl.SDL_WINDOW_BORDERLESS
        if o.mode is None:
            if sdl.SDL_GetDesktopDisplayMode(o.display, ctypes.byref(mode)) != 0:
                raise self._fail(sdl, f"desktop mode of display {o.display}")
            flags |= sdl.SDL_WINDOW_FULLSCREEN_DESKTOP
        else:
            want = sdl.SDL_DisplayMode(0, o.mode[0], o.mode[1], round(o.refresh_hz or 0))
            got = sdl.SDL_GetClosestDisplayMode(o.display, ctypes.byref(want), ctypes.byref(mode))
            if not got or (mode.w, mode.h) != o.mode:
                raise DeviceFault(self.name, f"display {o.display} offers no {o.mode[0]}x{o.mode[1]} mode")
            if o.refresh_hz and abs(mode.refresh_rate - o.refresh_hz) > 0.5:
                raise DeviceFault(self.name, f"display {o.display} offers no {o.refresh_hz:g} Hz at {o.mode}")
            flags |= sdl.SDL_WINDOW_FULLSCREEN
        pos = sdl.SDL_WINDOWPOS_UNDEFINED_DISPLAY(o.display)
        h["window"] = sdl.SDL_CreateWindow(self.name.encode(), pos, pos, mode.w, mode.h, flags)
        if not h["window"]:
            raise self._fail(sdl, "create window")
        if o.mode is not None and sdl.SDL_SetWindowDisplayMode(h["window"], ctypes.byref(mode)) != 0:
            raise self._fail(sdl, "set display mode")
        index = -1
        if o.renderer:
            names = []
            for i in range(sdl.SDL_GetNumRenderDrivers()):
                info = sdl.SDL_RendererInfo()
                sdl.SDL_GetRenderDriverInfo(i, ctypes.byref(info))
                names.append(info.name.decode())
            if o.renderer not in names:
                raise DeviceFault(self.name, f"SDL renderer {o.renderer!r} not available; have {names}")
            index = names.index(o.renderer)
        rflags = sdl.SDL_RENDERER_PRESENTVSYNC if o.vsync else 0
        h["renderer"] = sdl.SDL_CreateRenderer(h["window"], index, rflags)
        if not h["renderer"]:
            raise self._fail(sdl, "create renderer")
        info = sdl.SDL_RendererInfo()
        sdl.SDL_GetRendererInfo(h["renderer"], ctypes.byref(info))
        self._renderer_name = info.name.decode()
        self._vsync = bool(info.flags & sdl.SDL_RENDERER_PRESENTVSYNC)
        ow, oh = ctypes.c_int(), ctypes.c_int()
        sdl.SDL_GetRendererOutputSize(h["renderer"], ctypes.byref(ow), ctypes.byref(oh))
        if (ow.value, oh.value) != (mode.w, mode.h):
            raise DeviceFault(
                self.name,
                f"renderer output {ow.value}x{oh.value} differs from the mode {mode.w}x{mode.h} (desktop "
                "scaling or high-DPI): images would be resampled; set the desktop scale to 100 %",
            )
        h["texture"] = sdl.SDL_CreateTexture(
            h["renderer"], sdl.SDL_PIXELFORMAT_ARGB8888, sdl.SDL_TEXTUREACCESS_STREAMING, mode.w, mode.h
        )
        if not h["texture"]:
            raise self._fail(sdl, "create texture")
        sdl.SDL_SetTextureScaleMode(h["texture"], sdl.SDL_ScaleModeNearest)
        sdl.SDL_SetTextureBlendMode(h["texture"], sdl.SDL_BLENDMODE_NONE)
        sdl.SDL_ShowCursor(sdl.SDL_DISABLE)
        self._size = (mode.w, mode.h)
        self._refresh_hz = float(mode.refresh_rate)

    def _present(self, sdl: Any, h: dict[str, Any], image: NDArray[np.uint8]) -> float:
        w, hgt = image.shape[1], image.shape[0]
        argb = np.uint32(0xFF000000) | image.astype(np.uint32) * np.uint32(0x010101)  # opaque grey, R=G=B
        ptr = argb.ctypes.data_as(ctypes.c_void_p)
        if sdl.SDL_UpdateTexture(h["texture"], None, ptr, w * 4) != 0:
            raise self._fail(sdl, "upload")
        if sdl.SDL_RenderCopy(h["renderer"], h["texture"], None, None) != 0:
            raise self._fail(sdl, "copy")
        if self.options.readback:  # before the flip: the back buffer is defined only until it is presented
            rgb = np.empty((hgt, w, 3), np.uint8)
            out = rgb.ctypes.data_as(ctypes.c_void_p)
            if sdl.SDL_RenderReadPixels(h["renderer"], None, sdl.SDL_PIXELFORMAT_RGB24, out, w * 3) != 0:
                raise self._fail(sdl, "read back")
        sdl.SDL_RenderPresent(h["renderer"])
        stamp = time.monotonic()
        if self.options.readback:
            self._rgb = rgb
        self.present_count += 1
        self.last_present_s = stamp
        return stamp

    def _teardown(self, sdl: Any, h: dict[str, Any]) -> None:
        if h.get("texture"):
            sdl.SDL_DestroyTexture(h["texture"])
        if h.get("renderer"):
            sdl.SDL_DestroyRenderer(h["renderer"])
        if h.get("window"):
            sdl.SDL_DestroyWindow(h["window"])
        if h.get("video"):
            sdl.SDL_QuitSubSystem(sdl.SDL_INIT_VIDEO)
        h.clear()


def open_at_projector_resolution(display: Any, resolution: tuple[int, int], projector: str) -> None:
    """Open a projector's pattern display and refuse an output mode other than the projector's input
    resolution (patterns are pixel-exact: a scaled image would blur every stripe edge)."""
    display.open()
    if tuple(display.size) != tuple(resolution):
        display.close()
        raise DeviceFault(
            projector,
            f"HDMI display mode is {display.size[0]}x{display.size[1]} but the projector is "
            f"{resolution[0]}x{resolution[1]}; set the output to the projector's native mode "
            "(options.display.mode) or fix width_px/height_px",
        )
