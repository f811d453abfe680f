"""Build the Blender extension zip.

Stages dcc_client/blender_extension/hand_retarget/ together with the project's standard-library
modules dcc_client/client.py and dcc_client/curves.py (kept in one place in the repository,
copied in here because Blender's ``build`` skips symlinks and paths outside the source folder),
then runs Blender's extension command-line tool ``build`` and ``validate`` with the Python of
the ``bpy`` environment (no ``blender`` binary needed; dcc_client/BLENDER_NOTES.md, section 6).

    python dcc_client/build_extension.py [--out dist] [--blender-python .venv-blender/bin/python]

Prints the zip's path; exits non-zero when building or validating fails.
"""

from __future__ import annotations

import argparse
import os
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

HERE = Path(__file__).resolve().parent
REPO = HERE.parent
SOURCE = HERE / "blender_extension" / "hand_retarget"
STAGED_MODULES = ("client.py", "curves.py")
CLI = ("import sys, bpy; from bl_pkg.bl_extension_cli import cli_extension_handler; "
       "sys.exit(cli_extension_handler(sys.argv[1:]))")


def stage(dest: Path) -> Path:
    """Copy the extension and the staged modules into ``dest``/hand_retarget; returns that folder."""
    target = Path(dest) / SOURCE.name
    if target.exists():
        shutil.rmtree(target)
    shutil.copytree(SOURCE, target, ignore=shutil.ignore_patterns("__pycache__", "*.pyc", ".*"))
    for name in STAGED_MODULES:
        if (target / name).exists():
            raise SystemExit(f"{SOURCE / name} must not exist: {name} is staged from dcc_client/")
        shutil.copy2(HERE / name, target / name)
    return target


def run_cli(python: str, *args: str) -> str:
    with tempfile.TemporaryDirectory(prefix="hr_bpy_user_") as user:
        # ``import bpy`` writes its user folder and thumbnail caches under $HOME unless told otherwise
        env = dict(os.environ)
        env.setdefault("BLENDER_USER_RESOURCES", user)
        env.setdefault("XDG_CACHE_HOME", os.path.join(user, "cache"))
        proc = subprocess.run([python, "-c", CLI, *args], capture_output=True, text=True, env=env)
    out = proc.stdout + proc.stderr
    if proc.returncode != 0:
        raise SystemExit(f"blender extension {args[0]} failed ({proc.returncode}):\n{out}")
    return out


def build(out_dir, python: str | None = None) -> Path:
    """Stage, build and validate; returns the zip's path."""
    python = python or str(REPO / ".venv-blender" / "bin" / "python")
    out_dir = Path(out_dir).resolve()
    out_dir.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(prefix="hr_ext_") as tmp:
        src = stage(Path(tmp))
        run_cli(python, "validate", str(src))
        log = run_cli(python, "build", "--source-dir", str(src), "--output-dir", str(out_dir))
    zips = sorted(out_dir.glob("hand_retarget-*.zip"), key=lambda p: p.stat().st_mtime)
    if not zips:
        raise SystemExit(f"the build wrote no zip into {out_dir}:\n{log}")
    run_cli(python, "validate", str(zips[-1]))
    return zips[-1]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", default=str(REPO / "dist"), help="output folder (default: dist/)")
    ap.add_argument("--blender-python", default=None,
                    help="Python with the bpy module (default: .venv-blender/bin/python)")
    args = ap.parse_args(argv)
    print(build(args.out, args.blender_python))
    return 0


if __name__ == "__main__":
    sys.exit(main())
