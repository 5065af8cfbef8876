"""Fake `pyvcam.pvc`: library state and the list of attached cameras (a test sets `CAMERAS`)."""

#: name -> properties of each attached camera: sensor (H, W), bit_depth, temperature_c,
#: exposure limits in ms (min, max).
CAMERAS = {
    "PrimeBSI-fake": {"sensor": (40, 48), "bit_depth": 12, "temperature_c": -20.0, "exposure_ms": (0, 60000)},
}

_state = {"initialised": False, "open": set()}


def _require_init():
    if not _state["initialised"]:
        raise RuntimeError("PVCAM not initialised (call pvc.init_pvcam() first)")


def init_pvcam():
    if _state["initialised"]:
        raise RuntimeError("PVCAM already initialised")
    _state["initialised"] = True


def uninit_pvcam():
    _require_init()
    _state["initialised"] = False
    _state["open"].clear()


def get_cam_total():
    _require_init()
    return len(CAMERAS)


def get_cam_name(index):
    _require_init()
    return list(CAMERAS)[index]


def open_camera(name):
    _require_init()
    if name in _state["open"]:
        raise RuntimeError(f"camera {name} already open")
    _state["open"].add(name)
    return len(_state["open"])


def close_camera(name):
    _require_init()
    _state["open"].discard(name)


def is_initialised():
    """Not PyVCAM's: lets the tests check that the backend released the library."""
    return _state["initialised"]


def open_cameras():
    """Not PyVCAM's: the names of the cameras open now."""
    return set(_state["open"])
