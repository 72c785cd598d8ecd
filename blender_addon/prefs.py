# SPDX-License-Identifier: GPL-3.0-or-later
"""Add-on preferences (Edit > Preferences > Add-ons > Adv3D): the default paths the panels
start from and the runner the Scenes panel's "Attack this scene" starts.

A panel's own path (saved with the .blend) wins; an empty one falls back to these. When the
add-on is registered without an add-on entry (``blender_addon.register()`` from a script) the
defaults below apply.
"""
from __future__ import annotations

import os
import shutil
import sys
from pathlib import Path

import bpy
from bpy.props import StringProperty

PACKAGE = __package__  # "bl_ext.<repo>.adv3d" when installed as an extension


class ADV3D_AP_preferences(bpy.types.AddonPreferences):
    bl_idname = PACKAGE

    default_library: StringProperty(
        name="Default library", subtype="FILE_PATH",
        description="library.json the Library panel uses when it has none of its own")
    default_space: StringProperty(
        name="Default shape space", subtype="FILE_PATH",
        description="Shape-space .npz the Shape space panel uses when it has none of its own")
    runs_folder: StringProperty(
        name="Runs folder", subtype="DIR_PATH",
        description="Where \"Attack this scene\" writes its run bundles (default: ~/adv3d-runs)")
    runner: StringProperty(
        name="Runner", subtype="FILE_PATH",
        description="The adv3d runner: the `adv3d` command, or a Python interpreter that has adv3d installed "
                    "(default: `adv3d` on the PATH). Attacks run in it, outside Blender")

    def draw(self, context):
        layout = self.layout
        for name in ("default_library", "default_space", "runs_folder", "runner"):
            layout.prop(self, name)
        cmd = runner_command(self.runner)
        layout.label(text="Runner: " + (" ".join(cmd) if cmd else "not found (install adv3d or set Runner)"),
                     icon="CONSOLE")


classes = (ADV3D_AP_preferences,)


def get(context=None):
    """The add-on's preferences, or None when it has no add-on entry (script registration)."""
    context = context or bpy.context
    entry = context.preferences.addons.get(PACKAGE)
    return None if entry is None else entry.preferences


def value(name: str, context=None) -> str:
    """A preference's value ('' when unset or when the add-on has no entry)."""
    p = get(context)
    return "" if p is None else getattr(p, name)


#: Starter data the extension zip carries (``adv3d blender build``): the bundled library and the
#: shipped shape space, used when neither a panel nor the preferences name one.
STARTER = Path(__file__).resolve().parent / "starter"
STARTER_LIBRARY = STARTER / "vehicles" / "library.json"
STARTER_SPACE = STARTER / "shape_space" / "vehicles_64.npz"


def default_library(context=None) -> str:
    """The preferences' library, else the extension's starter library ('' when neither)."""
    if value("default_library", context):
        return bpy.path.abspath(value("default_library", context))
    return str(STARTER_LIBRARY) if STARTER_LIBRARY.is_file() else ""


def default_space(context=None) -> str:
    """The preferences' shape space, else the extension's starter space ('' when neither)."""
    if value("default_space", context):
        return bpy.path.abspath(value("default_space", context))
    return str(STARTER_SPACE) if STARTER_SPACE.is_file() else ""


def runs_folder(context=None) -> Path:
    folder = value("runs_folder", context)
    return Path(bpy.path.abspath(folder)) if folder else Path.home() / "adv3d-runs"


def runner_command(setting: str | None = None) -> list[str]:
    """The command that starts the runner CLI: ``[adv3d]`` or ``[python, -m, adv3d_runner.cli]``
    ([] when none is found)."""
    setting = value("runner") if setting is None else setting
    if not setting:
        found = shutil.which("adv3d")
        return [found] if found else []
    path = bpy.path.abspath(setting)
    name = os.path.basename(path).lower()
    if name.startswith("python") or name == os.path.basename(sys.executable).lower():
        return [path, "-m", "adv3d_runner.cli"]
    return [path]
