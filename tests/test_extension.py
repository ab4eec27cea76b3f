"""The extension: valid manifest (Blender's own validator), registers/unregisters twice as a module,
and installs from the zip Blender's own build tool makes, enabling and disabling twice."""
import sys
import tomllib
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parent.parent


def _blender_ext():
    from sg_lightfield.headless.build_extension import blender_ext_script

    script = blender_ext_script()
    sys.path.insert(0, str(script.parent))
    try:
        import blender_ext
    finally:
        sys.path.remove(str(script.parent))
    return blender_ext


def test_manifest_is_valid_for_blender_4_2_and_up():
    manifest = REPO / "blender_manifest.toml"
    errors = _blender_ext().pkg_manifest_from_toml_and_validate_all_errors(str(manifest), strict=True)
    assert not isinstance(errors, list), errors
    data = tomllib.loads(manifest.read_text())
    assert data["id"] == "sg_lightfield" and data["blender_version_min"] == "4.2.0"
    assert data["type"] == "add-on"


def test_register_unregister_twice_as_module():
    import bpy

    from sg_lightfield import blender_addon

    for _ in range(2):
        blender_addon.register()
        assert hasattr(bpy.types.Scene, "sg_lightfield")
        assert bpy.context.scene.sg_lightfield.preset == "DRAFT"
        assert hasattr(bpy.types, "SGLF_PT_render") and hasattr(bpy.types, "SGLF_PT_sidebar")
        assert bpy.ops.sg_lightfield.bake.poll()
        blender_addon.unregister()
        assert not hasattr(bpy.types.Scene, "sg_lightfield")
        assert not hasattr(bpy.types, "SGLF_PT_render")


def test_extension_zip_installs_and_toggles_twice(tmp_path):
    import addon_utils
    import bpy

    from sg_lightfield.headless.build_extension import build

    zip_path = build(tmp_path / "dist")
    names = set(__import__("zipfile").ZipFile(zip_path).namelist())
    assert {"blender_manifest.toml", "__init__.py", "blender_addon/ui.py", "shaders/sg_math.py"} <= names
    assert not any(n.startswith(("tests/", ".venv/", ".git/")) for n in names)
    # The add-on's imports that Blender does not ship travel as wheels (make fetches them into .venv/wheels).
    bundled = {n.split("/")[1].split("-")[0] for n in names if n.startswith("wheels/")}
    assert bundled == {"openexr", "xatlas", "pillow", "onnxruntime"}
    manifest = __import__("zipfile").ZipFile(zip_path).read("blender_manifest.toml").decode()
    assert 'platforms = ["linux-x64"]' in manifest and manifest.count("./wheels/") == 4
    result = bpy.ops.extensions.package_install_files(filepath=str(zip_path), repo="user_default",
                                                      enable_on_install=True)
    assert result == {"FINISHED"}
    module = "bl_ext.user_default.sg_lightfield"
    try:
        assert hasattr(bpy.types.Scene, "sg_lightfield")
        for _ in range(2):
            addon_utils.disable(module, default_set=True)
            assert not hasattr(bpy.types.Scene, "sg_lightfield")
            addon_utils.enable(module, default_set=True)
            assert hasattr(bpy.types.Scene, "sg_lightfield")
    finally:
        addon_utils.disable(module, default_set=True)
    assert not hasattr(bpy.types.Scene, "sg_lightfield")


NUMPY_SIDE = sorted(f"{package}.{path.stem}" for package in ("shaders", "bake_directory", "hair")
                    for path in (REPO / package).glob("*.py")
                    if path.stem not in ("__init__", "unet", "train", "blender_scene"))


def test_numpy_side_covers_the_packages():
    assert {"bake_directory.bake_plan", "bake_directory.texel_maps", "shaders.node_group", "hair.filtering"} <= set(NUMPY_SIDE)


@pytest.mark.parametrize("module", NUMPY_SIDE)
def test_numpy_side_imports_without_torch_or_bpy(module):
    import subprocess

    code = ("import sys; sys.modules['torch'] = None; sys.modules['bpy'] = None\n"
            "import sg_launch; sg_launch.load_package()\n"
            f"import importlib; importlib.import_module('sg_lightfield.' + {module!r}); print('ok')")
    out = subprocess.run([sys.executable, "-c", code], cwd=REPO, capture_output=True, text=True)
    assert out.returncode == 0 and out.stdout.strip() == "ok", out.stderr
