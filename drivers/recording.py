"""Recording proxy: wraps any device, passes every call through and writes a replayable fixture.

Fixture format 1 (docs/fixtures.md): a directory with ``fixture.yaml`` (device kind, name, read-only
properties, and the ordered list of calls with their arguments and results or errors) and ``arrays.npz``
(every numpy array -- frames, poses, joints -- referenced from the YAML as ``{$array: aN}``). Value types of
cell.contracts are written as ``{$type: Name, ...fields}``, enums as ``{$enum: Name, value: ...}``, and a
raised CellError as ``{$error: ClassName, device, message}``. :mod:`fakes.replay` serves it back.
"""

from __future__ import annotations

import copy
import dataclasses
import datetime
from enum import Enum
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from cell import contracts, errors
from cell.contracts import Camera, GlassRig, Projector, ProjectorHooks, Robot
from cell.devices import DeviceBundle

FIXTURE_FORMAT = 1
PROPERTIES = {
    "camera": ("name", "serial", "model", "resolution"),
    "projector": ("name", "resolution"),
    "robot": ("name", "envelope"),
}


def device_kind(device: Any) -> str:
    """'camera', 'projector' or 'robot' from the contract the device satisfies."""
    for kind, proto in (
        ("robot", Robot),
        ("projector", Projector),
        ("camera", Camera),
        ("glass_rig", GlassRig),
    ):
        if isinstance(device, proto):
            return kind
    raise TypeError(f"{type(device).__name__} satisfies no device contract of cell.contracts")


class _Encoder:
    """Turns call values into YAML-safe data, collecting arrays for the .npz."""

    def __init__(self) -> None:
        self.arrays: dict[str, np.ndarray] = {}

    def __call__(self, v: Any) -> Any:
        if isinstance(v, np.ndarray):
            key = f"a{len(self.arrays)}"
            self.arrays[key] = v
            return {"$array": key}
        if isinstance(v, Enum):
            return {"$enum": type(v).__name__, "value": v.value}
        if dataclasses.is_dataclass(v) and not isinstance(v, type):
            return {
                "$type": type(v).__name__,
                **{f.name: self(getattr(v, f.name)) for f in dataclasses.fields(v)},
            }
        if isinstance(v, errors.CellError):
            return {"$error": type(v).__name__, "device": getattr(v, "device", None), "message": str(v)}
        if isinstance(v, list | tuple):
            return [self(x) for x in v]
        if isinstance(v, dict):
            return {str(k): self(x) for k, x in v.items()}
        if isinstance(v, np.generic):
            return v.item()
        return v


def decode(v: Any, arrays: Any) -> Any:
    """Inverse of the encoder; tuples come back as tuples where the value types declare them."""
    if isinstance(v, list):
        return tuple(decode(x, arrays) for x in v)
    if isinstance(v, dict):
        if "$array" in v:
            return np.array(arrays[v["$array"]])
        if "$enum" in v:
            return getattr(contracts, v["$enum"])(v["value"])
        if "$type" in v:
            cls = getattr(contracts, v["$type"])
            return cls(**{k: decode(x, arrays) for k, x in v.items() if k != "$type"})
        if "$error" in v:
            cls = getattr(errors, v["$error"])
            if issubclass(cls, errors.DeviceError):
                return cls(v["device"], v["message"].split(": ", 1)[-1])
            return cls(v["message"])
        return {k: decode(x, arrays) for k, x in v.items()}
    return v


class RecordingProxy(ProjectorHooks):
    """``RecordingProxy(real_device)`` acts as it, recording each call; :meth:`save` writes the fixture. A
    projector's hooks (:class:`cell.contracts.ProjectorHooks`) run on the proxy, so the fixture holds the
    primitive calls they make, which is what the replay projector answers."""

    def __init__(self, device: Any) -> None:
        self._device = device
        self._kind = device_kind(device)
        self._calls: list[tuple[str, tuple[Any, ...], dict[str, Any], Any, BaseException | None]] = []
        self.name = device.name

    def __getattr__(self, attr: str) -> Any:
        value = getattr(self._device, attr)
        if not callable(value):
            return value

        def call(*args: Any, **kwargs: Any) -> Any:
            try:
                result = value(*args, **kwargs)
            except errors.CellError as exc:
                self._calls.append((attr, args, kwargs, None, exc))
                raise
            self._calls.append((attr, args, kwargs, result, None))
            return result

        return call

    # contract properties must be real attributes for isinstance() checks of Protocols
    @property
    def resolution(self) -> Any:
        return self._device.resolution

    @property
    def serial(self) -> Any:
        return self._device.serial

    @property
    def model(self) -> Any:
        return self._device.model

    @property
    def envelope(self) -> Any:
        return self._device.envelope

    @property
    def cameras(self) -> Any:
        return self._device.cameras

    @property
    def screen(self) -> Any:
        return self._device.screen

    def save(self, path: str | Path) -> Path:
        """Write ``path/fixture.yaml`` and ``path/arrays.npz``; returns the directory."""
        out = Path(path)
        out.mkdir(parents=True, exist_ok=True)
        enc = _Encoder()
        props = {p: enc(getattr(self._device, p)) for p in PROPERTIES.get(self._kind, ("name",))}
        calls = []
        for method, args, kwargs, result, error in self._calls:
            entry: dict[str, Any] = {"method": method, "args": enc(list(args))}
            if kwargs:
                entry["kwargs"] = enc(kwargs)
            entry["error" if error is not None else "result"] = enc(error if error is not None else result)
            calls.append(entry)
        doc = {
            "format": FIXTURE_FORMAT,
            "kind": self._kind,
            "device_class": type(self._device).__name__,
            "recorded_utc": datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds"),
            "properties": props,
            "calls": calls,
        }
        (out / "fixture.yaml").write_text(yaml.safe_dump(doc, sort_keys=False), encoding="utf-8")
        np.savez_compressed(out / "arrays.npz", **enc.arrays)  # type: ignore[arg-type]  # mypy maps **arrays onto allow_pickle
        return out


def record_bundle(devices: DeviceBundle) -> DeviceBundle:
    """The same cell with every device behind a :class:`RecordingProxy` (a simulated world stays reachable
    as ``sim``, so a recorded simulated run renders what an unrecorded one would)."""
    return dataclasses.replace(
        devices,
        robot=RecordingProxy(devices.robot),
        camera=RecordingProxy(devices.camera),
        projector=RecordingProxy(devices.projector),
    )


def save_bundle(devices: DeviceBundle, out: str | Path, cell_config: dict[str, Any]) -> Path:
    """Write one fixture per device under ``out`` (``robot/``, ``camera/``, ``projector/``) and ``cell.yaml``:
    ``cell_config`` (the cell config's YAML data) with every driver set to ``replay`` on those fixtures, so
    that ``cell inspect RECIPE --cell out/cell.yaml`` runs the recorded session again without hardware."""
    root = Path(out).resolve()
    data = copy.deepcopy(cell_config)
    sections = {
        "robot": data.setdefault("robot", {}),
        "camera": data.setdefault("sensor", {}).setdefault("camera", {}),
        "projector": data["sensor"].setdefault("projector", {}),
    }
    for kind, section in sections.items():
        proxy = getattr(devices, kind)
        if not isinstance(proxy, RecordingProxy):
            raise TypeError(f"the {kind} is not recorded: build the bundle with record_bundle()")
        fixture = proxy.save(root / kind)
        section["driver"] = "replay"
        section["options"] = {**(section.get("options") or {}), "fixture": str(fixture)}
    (root / "cell.yaml").write_text(yaml.safe_dump(data, sort_keys=False), encoding="utf-8")
    return root
