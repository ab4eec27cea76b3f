"""EXR helpers on real files: round trips, metadata, atomic writes, clear errors naming the file."""
import os

import numpy as np
import pytest

from sg_lightfield.bake_directory.exr_io import ExrError, read_exr, read_exr_metadata, write_exr


@pytest.mark.parametrize("channels", [1, 3, 4, 7])
@pytest.mark.parametrize("precision, tol", [("float", 0.0), ("half", 1e-3)])
def test_roundtrip(tmp_path, channels, precision, tol):
    rng = np.random.default_rng(channels)
    data = rng.uniform(-2, 2, size=(9, 13, channels)).astype(np.float32)
    path = write_exr(tmp_path / "sub" / "img.exr", data, precision=precision, metadata={"plan_hash": "abc123"})
    back, names, meta = read_exr(path)
    assert back.shape == (9, 13, channels) and len(names) == channels
    np.testing.assert_allclose(back, data, rtol=tol, atol=tol)
    assert meta == {"plan_hash": "abc123"} == read_exr_metadata(path)  # the header alone gives the same


def test_row_zero_is_the_top_scanline_and_channel_names_kept(tmp_path):
    data = np.zeros((4, 3, 2), np.float32)
    data[0, :, 0] = 1
    write_exr(tmp_path / "a.exr", data, precision="float", channels=["lf.axis_x", "lf.axis_y"])
    back, names, _ = read_exr(tmp_path / "a.exr", channels=["lf.axis_x", "lf.axis_y"])
    assert names == ["lf.axis_x", "lf.axis_y"]
    assert back[0, 0, 0] == 1 and back[1:, :, 0].sum() == 0


def test_half_clamps_overflow_instead_of_writing_inf(tmp_path):
    write_exr(tmp_path / "hdr.exr", np.full((2, 2, 3), 1e6, np.float32), precision="half")
    back, _, _ = read_exr(tmp_path / "hdr.exr")
    assert np.all(np.isfinite(back)) and np.all(back == np.float32(np.finfo(np.float16).max))


def test_atomic_write_leaves_no_temp_files(tmp_path):
    for _ in range(3):
        write_exr(tmp_path / "x.exr", np.ones((2, 2)), precision="half")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["x.exr"]
    mask = os.umask(0o022)
    os.umask(mask)
    assert (tmp_path / "x.exr").stat().st_mode & 0o777 == 0o666 & ~mask  # not private like a temp file


def test_missing_file_names_it(tmp_path):
    for reader in (read_exr, read_exr_metadata):
        with pytest.raises(ExrError, match="nothere.exr: EXR file not found"):
            reader(tmp_path / "nothere.exr")


def test_corrupt_and_truncated_files_name_it(tmp_path):
    (tmp_path / "junk.exr").write_bytes(b"not an exr at all")
    for reader in (read_exr, read_exr_metadata):
        with pytest.raises(ExrError, match="junk.exr"):
            reader(tmp_path / "junk.exr")
    good = write_exr(tmp_path / "good.exr", np.random.default_rng(0).random((64, 64, 3)), precision="float")
    blob = good.read_bytes()
    (tmp_path / "cut.exr").write_bytes(blob[: len(blob) // 2])
    with pytest.raises(ExrError, match="cut.exr"):
        read_exr(tmp_path / "cut.exr")


def test_missing_channel_and_bad_shapes_are_clear(tmp_path):
    write_exr(tmp_path / "rgb.exr", np.zeros((2, 2, 3)), precision="half")
    with pytest.raises(ExrError, match=r"rgb.exr: missing channels \['A'\]"):
        read_exr(tmp_path / "rgb.exr", channels=["R", "A"])
    with pytest.raises(ExrError, match="bad.exr"):
        write_exr(tmp_path / "bad.exr", np.zeros((2, 2, 2, 2)))
    with pytest.raises(ExrError, match="names"):
        write_exr(tmp_path / "names.exr", np.zeros((2, 2, 2)), channels=["R"])


def test_unwritable_target_names_it(tmp_path):
    blocker = tmp_path / "file"
    blocker.write_text("x")
    with pytest.raises((ExrError, OSError), match="file"):
        write_exr(blocker / "inside.exr", np.zeros((2, 2)))
