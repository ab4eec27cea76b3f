"""The extension: valid manifest (Blender's own validator), registers/unregisters twice as a module, one zip per
platform from Blender's own build tool (each with its wheels, each validated), and the Linux zip installs and
enables and disables twice."""
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


def test_manifest_is_valid_for_blender_4_5_and_up():
    manifest = REPO / "blender_manifest.toml"
    errors = _blender_ext().pkg_manifest_from_toml_and_validate_all_errors(str(manifest), strict=True)
    assert not isinstance(errors, list), errors
    data = tomllib.loads(manifest.read_text())
    assert data["id"] == "sg_lightfield" and data["blender_version_min"] == "4.5.0"
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


WHEEL_TAGS = {"linux-x64": "manylinux", "windows-x64": "win_amd64", "macos-arm64": "arm64", "macos-x64": "x86_64"}


def test_one_zip_per_platform_each_with_its_own_wheels_passes_blenders_validator(tmp_path):
    import subprocess
    import zipfile

    from sg_lightfield.headless.build_extension import PLATFORM_TAGS, blender_ext_script, build_all

    zips = build_all(tmp_path / "dist")
    assert set(zips) == set(PLATFORM_TAGS) == {"linux-x64", "windows-x64", "macos-arm64", "macos-x64"}
    for platform, path in zips.items():
        archive = zipfile.ZipFile(path)
        manifest = tomllib.loads(archive.read("blender_manifest.toml").decode())
        generated = manifest["build"]["generated"]  # what Blender's split build wrote for this zip's platform
        assert generated["platforms"] == [platform]
        wheels = [n.split("/")[1] for n in archive.namelist() if n.startswith("wheels/")]
        for abi in ("cp311", "cp313"):  # Blender 4.5-5.0 and Blender 5.1 and later
            assert sorted(w.split("-")[0] for w in wheels if f"-{abi}-" in w) == [
                "onnxruntime", "openexr", "pillow", "xatlas"], (abi, wheels)
        assert len(wheels) == 8 and all(WHEEL_TAGS[platform] in w for w in wheels), (platform, wheels)
        assert sorted(f"./wheels/{w}" for w in wheels) == sorted(generated["wheels"])
        assert "models/hair_large.onnx" in archive.namelist() and not any(
            n.startswith(("tests/", ".venv/", ".git/")) for n in archive.namelist())
        check = subprocess.run([sys.executable, str(blender_ext_script()), "validate", str(path)],
                               capture_output=True, text=True)
        assert check.returncode == 0, (platform, check.stdout, check.stderr)
    onnxruntime = {p: next(n for n in zipfile.ZipFile(z).namelist() if "onnxruntime-" in n) for p, z in zips.items()}
    assert "onnxruntime-1.23.2-" in onnxruntime["macos-x64"]  # the last Intel-macOS onnxruntime
    assert manifest["permissions"]["network"]  # Install Training Runtime downloads only with this permission


def test_extension_zip_installs_and_toggles_twice(tmp_path):
    import bpy  # first: importing bpy puts Blender's script modules (addon_utils) on the path

    import addon_utils

    from sg_lightfield.headless.build_extension import build

    zip_path = build(tmp_path / "dist", platform="linux-x64")
    names = set(__import__("zipfile").ZipFile(zip_path).namelist())
    assert {"blender_manifest.toml", "__init__.py", "blender_addon/ui.py", "shaders/sg_math.py",
            "bake_directory/bake_plan.py", "hair/filtering.py"} <= names
    # The add-on's imports that Blender does not ship travel as wheels (make fetches them into .venv/wheels).
    bundled = {n.split("/")[1].split("-")[0] for n in names if n.startswith("wheels/")}
    assert bundled == {"openexr", "xatlas", "pillow", "onnxruntime"}
    generated = tomllib.loads(__import__("zipfile").ZipFile(zip_path).read("blender_manifest.toml").decode())[
        "build"]["generated"]
    assert generated["platforms"] == ["linux-x64"] and len(generated["wheels"]) == 8
    result = bpy.ops.extensions.package_install_files(filepath=str(zip_path), repo="user_default",
                                                      enable_on_install=True)
    assert result == {"FINISHED"}
    module = "bl_ext.user_default.sg_lightfield"
    try:
        assert hasattr(bpy.types.Scene, "sg_lightfield")
        # inside the installed extension the runtime has a user directory to go to, so the install is offered
        assert bpy.ops.sg_lightfield.install_training_runtime.poll()
        assert not bpy.ops.sg_lightfield.remove_training_runtime.poll()  # nothing installed yet
        user_dir = bpy.utils.extension_path_user(module, create=True)
        assert Path(user_dir).is_dir() and "sg_lightfield" in user_dir
        online = bpy.context.preferences.system.use_online_access
        bpy.context.preferences.system.use_online_access = False
        try:  # without online access the install refuses, before anything is made or downloaded
            with pytest.raises(RuntimeError, match="does not allow online access"):
                bpy.ops.sg_lightfield.install_training_runtime("EXEC_DEFAULT")
        finally:
            bpy.context.preferences.system.use_online_access = online
        assert not (Path(user_dir) / "training_runtime").exists()
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
