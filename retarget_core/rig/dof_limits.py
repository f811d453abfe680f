"""DOF limits as a small TOML file by joint name, for a user to inspect and edit the DOFs a rig
was given (``handretarget rig import``): one table per joint, one ``dof = [lower, upper]``
per DOF, degrees for rotations and metres for translations.

    [index1]
    index1_flex = [-45.0, 90.0]
    index1_abduct = [-20.0, 20.0]

Reading it back (:func:`apply_limits`) changes only the limits it names; a joint or DOF the rig
does not have, a malformed pair, or a range that no longer holds the DOF's rest value is an
InputError naming the entry."""

from __future__ import annotations

import tomllib
from dataclasses import replace
from pathlib import Path

import numpy as np

from ..errors import InputError
from .model import Rig


def _toml_key(name: str) -> str:
    bare = name and all(c.isalnum() or c in "_-" for c in name)
    return name if bare else '"' + name.replace("\\", "\\\\").replace('"', '\\"') + '"'


def limits_toml(rig: Rig) -> str:
    """The rig's DOF limits as TOML text (see the module docstring); the free root is left out
    (its limits are the solver's search box, not the hand's)."""
    lines = [f"# DOF limits of rig {rig.name!r}: degrees for rotations, metres for translations.",
             "# Edit and pass back with `handretarget rig import FILE --limits THIS.toml --out RIG.usda`."]
    for j, joint in enumerate(rig.joints):
        dofs = [d for d in rig.dofs if d.joint == j and not (j == 0 and d.name.startswith("root_"))]
        if not dofs:
            continue
        lines.append("")
        lines.append(f"[{_toml_key(joint.name)}]")
        for d in dofs:
            scale = 180.0 / np.pi if d.kind == "rotate" else 1.0
            lines.append(f"{_toml_key(d.name)} = [{d.lower * scale:.4f}, {d.upper * scale:.4f}]")
    return "\n".join(lines) + "\n"


def apply_limits(rig: Rig, path) -> Rig:
    """A copy of ``rig`` with the limits of the TOML file ``path`` (see the module docstring)."""
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError as exc:
        raise InputError("no such file", source=str(path)) from exc
    except UnicodeDecodeError as exc:
        raise InputError(f"not a valid TOML file: {exc}", source=str(path)) from exc
    return apply_limits_text(rig, text, source=str(path), label=path.name)


def apply_limits_text(rig: Rig, text: str, *, source: str, label: str | None = None) -> Rig:
    """A copy of ``rig`` with the limits of the TOML ``text`` (see the module docstring);
    errors name ``source``; the rig's metadata records ``label`` as ``limits_from``."""
    src = source
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise InputError(f"not a valid TOML file: {exc}", source=src) from exc
    joints = {j.name: i for i, j in enumerate(rig.joints)}
    dofs = [replace(d, axis=np.array(d.axis, float)) for d in rig.dofs]
    by_name = {d.name: d for d in dofs}
    for joint, table in data.items():
        if joint not in joints or not isinstance(table, dict):
            raise InputError(f"rig {rig.name!r} has no joint {joint!r}" if joint not in joints
                             else "expected a table of DOF limits", source=src, element=f"[{joint}]")
        for name, pair in table.items():
            el = f"[{joint}] {name}"
            d = by_name.get(name)
            if d is None or d.joint != joints[joint]:
                raise InputError(f"joint {joint!r} has no DOF {name!r}", source=src, element=el)
            if (not isinstance(pair, list) or len(pair) != 2
                    or not all(isinstance(x, (int, float)) and np.isfinite(x) for x in pair)):
                raise InputError("expected [lower, upper], two finite numbers", source=src, element=el)
            scale = np.pi / 180.0 if d.kind == "rotate" else 1.0
            lower, upper = float(pair[0]) * scale, float(pair[1]) * scale
            if not lower < upper:
                raise InputError(f"lower {pair[0]} is not below upper {pair[1]}", source=src, element=el)
            if not lower <= d.rest <= upper:
                unit = "deg" if d.kind == "rotate" else "m"
                raise InputError(f"the range [{pair[0]}, {pair[1]}] {unit} leaves out the DOF's rest value "
                                 f"{d.rest / scale:.4g} {unit}", source=src, element=el)
            d.lower, d.upper = lower, upper
    out = replace(rig, dofs=dofs, metadata={**rig.metadata, "limits_from": label or source})
    out.validate(source=src)
    return out
