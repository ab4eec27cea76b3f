"""SG Lightfield add-on: registration of properties, operators and panels (bpy only)."""
from __future__ import annotations

from . import operators, properties, ui

_modules = (properties, operators, ui)


def register():
    for module in _modules:
        module.register()


def unregister():
    for module in reversed(_modules):
        module.unregister()
