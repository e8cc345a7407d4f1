"""GenICam SFNC settings both camera drivers (harvesters, Aravis) make the same way: auto features off and
the trigger nodes of a trigger mode. The drivers differ only in how they read and write a node, which they
pass in as ``has(name)`` and ``set_enum(name, value)`` (the latter checks the entry and reads it back)."""

from __future__ import annotations

from collections.abc import Callable, Collection

from cell.contracts import TriggerMode
from cell.errors import DeviceFault

AUTO_FEATURES = ("ExposureAuto", "GainAuto", "BalanceWhiteAuto")


def auto_features_off(has: Callable[[str], bool], set_enum: Callable[[str, str], None]) -> None:
    """Turn every automatic feature the camera has off: a scan's pattern and inverse need equal exposure."""
    for auto in AUTO_FEATURES:
        if has(auto):
            set_enum(auto, "Off")


def trigger_nodes(mode: TriggerMode) -> list[str]:
    """The SFNC nodes a trigger mode needs."""
    needed = ["TriggerMode"] if mode is TriggerMode.FREE_RUN else ["TriggerMode", "TriggerSource"]
    if mode is TriggerMode.SOFTWARE:
        needed.append("TriggerSoftware")
    if mode is TriggerMode.HARDWARE:
        needed += ["TriggerActivation", "LineSelector", "LineMode"]
    return needed


def configure_trigger(
    camera: str,
    model: str,
    mode: TriggerMode,
    *,
    has: Callable[[str], bool],
    set_enum: Callable[[str, str], None],
    ignore_missing: Collection[str] = (),
    line: str = "Line0",
    activation: str = "RisingEdge",
) -> None:
    """Set FrameStart triggering for ``mode``: software, or hardware on input ``line`` (LineMode Input,
    ``activation`` edge), or free run. A node the mode needs but the camera lacks (and the config does not
    allow to miss) is a DeviceFault naming the camera and the nodes, raised before anything is written."""
    missing = [n for n in trigger_nodes(mode) if not has(n) and n not in ignore_missing]
    if missing:
        raise DeviceFault(
            camera, f"{mode.value} trigger needs GenApi node(s) {', '.join(missing)}, absent on {model}"
        )
    if has("TriggerSelector"):
        set_enum("TriggerSelector", "FrameStart")
    if has("AcquisitionMode"):
        set_enum("AcquisitionMode", "Continuous")
    set_enum("TriggerMode", "Off" if mode is TriggerMode.FREE_RUN else "On")
    if mode is TriggerMode.SOFTWARE:
        set_enum("TriggerSource", "Software")
    elif mode is TriggerMode.HARDWARE:
        if has("LineSelector"):
            set_enum("LineSelector", line)
            set_enum("LineMode", "Input")
        set_enum("TriggerSource", line)
        if has("TriggerActivation"):
            set_enum("TriggerActivation", activation)
