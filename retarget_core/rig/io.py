"""Loading and saving rigs by file type: USD (.usd/.usda/.usdc), URDF (.urdf), MJCF (.xml/.mjcf)."""

from __future__ import annotations

from pathlib import Path

from ..errors import InputError
from .model import Rig

USD_SUFFIXES = (".usd", ".usda", ".usdc")
URDF_SUFFIXES = (".urdf",)
MJCF_SUFFIXES = (".xml", ".mjcf")


def load_rig(path, *, wrapper_resolution: float = 0.002, root_body: str | None = None, confine_to=None,
             mapping=None, hand_root: str | None = None) -> Rig:
    """Read a rig from USD, or import a robot hand from URDF or MJCF (which also builds its
    closed wrapper surface at ``wrapper_resolution`` metres). A plain UsdSkel file gets DOFs
    by role (:func:`~retarget_core.rig.usd_io.read_rig_usd`), settled by ``mapping`` (a
    :class:`~retarget_core.rig.hand_model.HandMapping`) where the hand model cannot tell, and
    a hand inside a larger skeleton is cut out below ``hand_root`` (or where its fingers branch).

    ``confine_to``: a folder (e.g. an unpacked upload) that every file the rig refers to must
    lie in (URDF/MJCF meshes and includes, USD sublayers, references and payloads); anything
    outside raises InputError naming the element and the reference as written, and is never
    opened. Errors then name files relative to that folder. None (the command line's
    default): local files load as written."""
    path = Path(path)
    shown = str(path)
    if confine_to is not None:
        from .robot_import import Confinement

        conf = Confinement(confine_to)
        path = conf.check_file(path, source=path.name, what="rig file")
        shown = conf.shown(path)
    if not path.is_file():
        raise InputError("no such file", source=shown)
    suffix = path.suffix.lower()
    if hand_root is not None and suffix not in USD_SUFFIXES:
        raise InputError(f"a hand root picks the hand inside a USD skeleton; {path.name} is not USD "
                         "(use --root-body for an MJCF model)", source=shown, element="hand_root")
    if root_body is not None and suffix not in MJCF_SUFFIXES:
        raise InputError(f"a root body picks the hand inside an MJCF model; {path.name} is not MJCF "
                         "(a URDF's hand is the tree below its root link; a USD hand is its Skeleton)",
                         source=shown, element="root_body")
    if suffix in USD_SUFFIXES:
        from .usd_io import read_rig_usd

        return read_rig_usd(path, confine_to=confine_to, mapping=mapping, hand_root=hand_root)
    if suffix in URDF_SUFFIXES:
        from .robot_import import load_urdf

        return load_urdf(path, wrapper_resolution=wrapper_resolution, confine_to=confine_to)
    if suffix in MJCF_SUFFIXES:
        from .robot_import import load_mjcf

        return load_mjcf(path, root_body=root_body, wrapper_resolution=wrapper_resolution, confine_to=confine_to)
    raise InputError(
        f"unknown rig file type {suffix!r}; expected one of "
        + ", ".join(USD_SUFFIXES + URDF_SUFFIXES + MJCF_SUFFIXES),
        source=shown,
    )


def save_rig(rig: Rig, path) -> None:
    """Write a rig as USD (.usda text or .usdc binary, by suffix)."""
    path = Path(path)
    if path.suffix.lower() not in USD_SUFFIXES:
        raise InputError("rigs are written as USD: use .usda, .usdc or .usd", source=str(path))
    from .usd_io import write_rig_usd

    write_rig_usd(rig, path)


#: Mesh cell sizes (m) a demo hand may be built at through ``demo:NAME@R``: [1 mm, 20 mm]. A
#: spec may come from untrusted input (a clip's ``source_rig`` field), and the hand's size grows
#: with the inverse cube of the cell (0.7 mm took 1.6 GB; 0 never ends).
DEMO_RESOLUTION_RANGE = (0.001, 0.02)
#: The cell size of ``demo:NAME`` without ``@R``.
DEMO_DEFAULT_RESOLUTION = 0.002


def demo_resolution(res: str, spec: str = "") -> float:
    """The cell size of a ``demo:NAME@R`` spec's ``R`` ("" = the default): a finite number of
    metres within :data:`DEMO_RESOLUTION_RANGE`, else InputError (element ``rig``)."""
    import math

    if not res:
        return DEMO_DEFAULT_RESOLUTION
    lo, hi = DEMO_RESOLUTION_RANGE
    try:
        resolution = float(res)
    except ValueError:
        resolution = float("nan")
    if not (math.isfinite(resolution) and lo <= resolution <= hi):
        raise InputError(f"bad resolution {res!r} in {spec!r}: a demo hand is built at {lo:g} to {hi:g} m "
                         f"(1 to 20 mm cells)", element="rig")
    return resolution


#: Robot hand models shipped by wheels installed at set-up (Makefile ROBOT_MODEL_WHEELS):
#: ``installed:NAME`` -> (package, path inside it). Only their files are used.
INSTALLED_MODELS = {
    "leap": ("ghand", "assets/models/urdf/ghand_right.urdf"),
    "shadow": ("gymnasium_robotics", "envs/assets/hand/reach.xml"),
}


def installed_model(name: str) -> Path:
    """The file of an installed robot hand model (see :data:`INSTALLED_MODELS`)."""
    import importlib.util

    if name not in INSTALLED_MODELS:
        raise InputError(f"unknown installed model {name!r}; known: {', '.join(INSTALLED_MODELS)}", element="rig")
    package, inner = INSTALLED_MODELS[name]
    try:
        spec = importlib.util.find_spec(package)
    except (ImportError, ValueError):
        spec = None
    locations = list(spec.submodule_search_locations or []) if spec is not None else []
    path = Path(locations[0]) / inner if locations else None
    if path is None or not path.is_file():
        raise InputError(f"the {name} model is not installed (its wheel {package!r} is installed by `make setup`)",
                         element="rig")
    return path


def resolve_rig(spec: str, **load_options) -> Rig:
    """A rig from a file path, a demo hand as ``demo:NAME`` or ``demo:NAME@RESOLUTION``
    (metres, within :data:`DEMO_RESOLUTION_RANGE`; the clip format records its source rig this
    way, e.g. "demo:source_human@0.004"), or an installed robot hand model as
    ``installed:NAME[@WRAPPER_RESOLUTION]`` (:data:`INSTALLED_MODELS`)."""
    spec = str(spec)
    if spec.startswith("installed:"):
        name, _, res = spec[len("installed:"):].partition("@")
        options = dict(load_options)
        if res:
            options["wrapper_resolution"] = demo_resolution(res, spec)
        return load_rig(installed_model(name), **options)
    if spec.startswith("demo:"):
        from .demo_hands import DEMO_HANDS, demo_hand

        name, _, res = spec[len("demo:"):].partition("@")
        if name not in DEMO_HANDS:
            raise InputError(f"unknown demo hand {name!r}; known: {', '.join(DEMO_HANDS)}", element="rig")
        if any(v is not None for v in load_options.values()):
            raise InputError(f"{spec}: a demo hand takes no rig options "
                             f"({', '.join(k for k, v in load_options.items() if v is not None)})", element="rig")
        return demo_hand(name, resolution=demo_resolution(res, spec))
    return load_rig(spec, **load_options)
