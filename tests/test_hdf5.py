"""The HDF5 dataset format (SPEC §5): round trip, other producers' files, atomic writing, bad input."""

from __future__ import annotations

import os

import h5py
import numpy as np
import pytest

from conftest import write_tiny_dataset
from hybridqcm.data import simulate as simulate_module
from hybridqcm.data.dataset_writer import DatasetWriter
from hybridqcm.data.hdf5 import LAYOUT, SCHEMA, dataset_info, read_split, recorded_channels
from hybridqcm.errors import DatasetError

ALL_KEYS = tuple(LAYOUT)


def random_split(m: int, n: int, seed: int = 0) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(seed)
    return {
        "accel": rng.normal(size=(m, n, 3)).astype(np.float32),
        "vel": rng.normal(size=(m, n, 3)).astype(np.float32),
        "disp": rng.normal(size=(m, n, 3)).astype(np.float32),
        "road": rng.normal(size=(m, n)).astype(np.float32),
        "params": rng.uniform(1, 2, size=(m, 10)),
        "road_class": rng.integers(0, 3, size=m).astype(np.int8),
        "profile_id": np.arange(m, dtype=np.int32),
        "state0": rng.normal(size=(m, 6)),
    }


def write_plain(path, splits: dict[str, dict[str, np.ndarray]], attrs: dict | None = None) -> None:
    """Another producer: plain h5py, no hybridqcm code."""
    with h5py.File(path, "w") as f:
        for k, v in (attrs or {}).items():
            f.attrs[k] = v
        for split, arrays in splits.items():
            for key, value in arrays.items():
                f.create_dataset(f"{split}/{key}", data=value)


def test_write_read_round_trip_is_exact(tmp_path):
    path = tmp_path / "rt.h5"
    train, test = random_split(37, 20, 1), random_split(11, 20, 2)
    with DatasetWriter(
        path, attrs={"h": 0.01, "n_steps": 20, "prior": "thesis", "seed": 3, "extra": {"a": [1, 2]}}, chunk_samples=8
    ) as writer:
        for split, arrays in (("train", train), ("test", test)):
            writer.create_split(split, arrays["params"].shape[0], 20)
            writer.write(split, 0, **{k: v[:10] for k, v in arrays.items()})  # written in two pieces
            writer.write(split, 10, **{k: v[10:] for k, v in arrays.items()})
    for split, arrays in (("train", train), ("test", test)):
        back = read_split(path, split, ALL_KEYS)
        assert back["h"] == 0.01
        for key in ALL_KEYS:
            assert back[key].dtype == LAYOUT[key][0]
            np.testing.assert_array_equal(back[key], arrays[key])
    info = dataset_info(path)
    assert info["attrs"]["schema"] == SCHEMA and info["attrs"]["seed"] == 3
    assert info["splits"]["train"] == {"n_samples": 37, "n_steps": 20, "keys": sorted(ALL_KEYS)}
    assert info["splits"]["test"]["n_samples"] == 11
    assert oct(os.stat(path).st_mode & 0o777) == oct(0o644)


def test_window_and_index(tmp_path):
    path = tmp_path / "w.h5"
    arrays = random_split(9, 30)
    write_plain(path, {"test": arrays})
    out = read_split(path, "test", ("accel", "road", "params"), n_steps=12)
    assert out["accel"].shape == (9, 12, 3) and out["road"].shape == (9, 12)
    np.testing.assert_array_equal(out["accel"], arrays["accel"][:, :12])
    # rows come back in the order asked for, repeats included
    idx = np.array([7, 2, 2, 0])
    out = read_split(path, "test", ("accel", "params", "road_class"), n_steps=5, index=idx)
    np.testing.assert_array_equal(out["accel"], arrays["accel"][idx, :5])
    np.testing.assert_array_equal(out["params"], arrays["params"][idx])
    np.testing.assert_array_equal(out["road_class"], arrays["road_class"][idx])
    out = read_split(path, "test", ("road",), index=slice(2, 5))
    np.testing.assert_array_equal(out["road"], arrays["road"][2:5])
    mask = np.zeros(9, bool)
    mask[[1, 4]] = True
    np.testing.assert_array_equal(read_split(path, "test", ("params",), index=mask)["params"], arrays["params"][mask])
    with pytest.raises(DatasetError, match="out of range"):
        read_split(path, "test", ("params",), index=np.array([0, 9]))


def test_reads_a_file_from_another_producer(tmp_path):
    """Plain h5py, SPEC §5 layout with only accel/road/params (and one without params, no attributes)."""
    full = random_split(6, 40, 5)
    path = tmp_path / "other.h5"
    write_plain(
        path,
        {"test": {k: full[k] for k in ("accel", "road", "params")}},
        attrs={"schema": SCHEMA, "h": 0.01, "n_steps": 40, "mass_range": np.array([30.0, 150.0])},
    )
    out = read_split(path, "test")  # default keys: accel, road, params
    for key in ("accel", "road", "params"):
        np.testing.assert_array_equal(out[key], full[key])
    assert out["h"] == 0.01
    info = dataset_info(path)
    assert info["splits"]["test"]["keys"] == ["accel", "params", "road"]
    assert info["attrs"]["mass_range"] == [30.0, 150.0]

    bare = tmp_path / "bare.h5"  # inference only: no params, no attributes at all, float64 arrays
    write_plain(bare, {"field": {"accel": full["accel"].astype(np.float64), "road": full["road"].astype(np.float64)}})
    out = read_split(bare, "field", ("accel", "road"), n_steps=32)
    np.testing.assert_array_equal(out["accel"], full["accel"][:, :32].astype(np.float64))
    assert "h" not in out
    with pytest.raises(DatasetError, match=r"lacks dataset\(s\) \['params'\]"):
        read_split(bare, "field", ("accel", "road", "params"))


def test_write_dataset_same_seed_identical_other_seed_different(tmp_path):
    a, b, c = tmp_path / "a.h5", tmp_path / "b.h5", tmp_path / "c.h5"
    small = {"train": {"profiles": {"A": 1, "C": 1}}, "test": {"profiles": {"B": 1}}}
    for path, seed in ((a, 4), (b, 4), (c, 5)):
        write_tiny_dataset(path, seed=seed, splits=small, n_steps=64)
    for split in ("train", "test"):
        xa, xb, xc = (read_split(p, split, ALL_KEYS) for p in (a, b, c))
        for key in ALL_KEYS:
            assert xa[key].tobytes() == xb[key].tobytes(), key
        assert not np.array_equal(xa["accel"], xc["accel"])
        assert not np.array_equal(xa["params"], xc["params"])


def test_tiny_dataset_fixture_content(tiny_dataset):
    info = dataset_info(tiny_dataset)
    assert info["attrs"]["schema"] == SCHEMA and info["attrs"]["h"] == 0.01 and info["attrs"]["n_steps"] == 512
    assert info["splits"]["train"]["n_samples"] == 48 and info["splits"]["test"]["n_samples"] == 40
    for split, counts in (("train", {0: 24, 1: 16, 2: 8}), ("test", {0: 16, 1: 16, 2: 8})):
        data = read_split(tiny_dataset, split, ALL_KEYS)
        assert data["accel"].shape == (info["splits"][split]["n_samples"], 512, 3)
        assert dict(zip(*np.unique(data["road_class"], return_counts=True))) == counts
        for pid in np.unique(data["profile_id"]):  # samples of one profile share road and class
            rows = data["profile_id"] == pid
            assert rows.sum() == 8
            assert (data["road"][rows] == data["road"][rows][0]).all()
            assert len(np.unique(data["road_class"][rows])) == 1
            assert len(np.unique(data["params"][rows][:, 1])) == 8  # 8 different draws


# --------------------------------------------------------------------------- atomic writing


def test_exception_mid_write_leaves_no_file(tmp_path):
    path = tmp_path / "x.h5"
    with pytest.raises(RuntimeError, match="boom"):
        with DatasetWriter(path) as writer:
            writer.create_split("train", 4, 10)
            writer.write("train", 0, road=np.zeros((2, 10), np.float32))
            # only the temporary file and the writer's lock exist meanwhile
            assert sorted(p.suffix for p in tmp_path.iterdir()) == [".lock", ".partial"]
            raise RuntimeError("boom")
    assert list(tmp_path.iterdir()) == []


def test_write_dataset_failure_in_a_later_chunk_leaves_no_file(tmp_path, monkeypatch):
    calls = {"n": 0}
    real = simulate_module.simulate_samples

    def failing(*args, **kwargs):
        calls["n"] += 1
        if calls["n"] == 3:
            raise FloatingPointError("simulated failure in chunk 3")
        return real(*args, **kwargs)

    monkeypatch.setattr(simulate_module, "simulate_samples", failing)
    with pytest.raises(FloatingPointError):
        write_tiny_dataset(tmp_path / "y.h5", n_steps=32)
    assert calls["n"] == 3 and list(tmp_path.iterdir()) == []


def test_failure_while_opening_leaves_no_temp_file(tmp_path):
    with pytest.raises(TypeError):
        with DatasetWriter(tmp_path / "z.h5", attrs={"bad": object()}):
            pass
    assert list(tmp_path.iterdir()) == []


def test_refuses_to_overwrite_unless_asked(tmp_path):
    path = tmp_path / "keep.h5"
    path.write_bytes(b"precious")
    with pytest.raises(FileExistsError, match="overwrite"):
        DatasetWriter(path)
    with pytest.raises(FileExistsError):
        write_tiny_dataset(path, n_steps=16)
    assert path.read_bytes() == b"precious"
    with DatasetWriter(path, overwrite=True) as writer:
        writer.create_split("test", 2, 5, keys=("road",))
        writer.write("test", 0, road=np.ones((2, 5), np.float32))
    np.testing.assert_array_equal(read_split(path, "test", ("road",))["road"], np.ones((2, 5), np.float32))
    with pytest.raises(DatasetError, match="directory"):
        DatasetWriter(tmp_path, overwrite=True)


def test_writer_rejects_bad_arrays(tmp_path):
    path = tmp_path / "bad.h5"
    with pytest.raises(DatasetError, match="non-finite"):
        with DatasetWriter(path) as writer:
            writer.create_split("train", 3, 4)
            writer.write("train", 0, accel=np.full((3, 4, 3), np.nan, np.float32))
    with pytest.raises(DatasetError, match=r"shape \(3, 5, 3\)"):
        with DatasetWriter(path) as writer:
            writer.create_split("train", 3, 4)
            writer.write("train", 0, accel=np.zeros((3, 5, 3), np.float32))
    with pytest.raises(DatasetError, match="at row 2"):
        with DatasetWriter(path) as writer:
            writer.create_split("train", 3, 4)
            writer.write("train", 2, road=np.zeros((2, 4), np.float32))
    with pytest.raises(DatasetError, match="compression"):
        DatasetWriter(path, compression="zip")
    assert list(tmp_path.iterdir()) == []


# --------------------------------------------------------------------------- bad input


@pytest.fixture
def good_file(tmp_path):
    path = tmp_path / "good.h5"
    write_plain(path, {"test": random_split(4, 16)}, attrs={"schema": SCHEMA, "h": 0.01})
    return path


def test_missing_file(tmp_path):
    path = tmp_path / "nope.h5"
    with pytest.raises(DatasetError, match=f"{path}: dataset file does not exist"):
        read_split(path)
    with pytest.raises(DatasetError, match="does not exist"):
        dataset_info(path)


def test_not_hdf5(tmp_path):
    path = tmp_path / "corrupt.h5"
    path.write_bytes(b"\x89HDF\r\n\x1a\n" + os.urandom(2000))
    with pytest.raises(DatasetError, match=f"{path}: not a readable HDF5 file"):
        read_split(path)
    truncated = tmp_path / "truncated.h5"
    write_plain(truncated, {"test": random_split(4, 16)})
    truncated.write_bytes(truncated.read_bytes()[:600])
    with pytest.raises(DatasetError, match="not a readable HDF5 file"):
        read_split(truncated)


def test_wrong_schema_version(tmp_path):
    path = tmp_path / "v3.h5"
    write_plain(path, {"test": random_split(2, 8)}, attrs={"schema": "hybridqcm.dataset/3"})
    with pytest.raises(DatasetError, match=r"v3.h5: attribute schema = 'hybridqcm.dataset/3' is not supported"):
        read_split(path)
    with pytest.raises(DatasetError, match="schema"):
        dataset_info(path)


def test_missing_split_and_dataset(good_file):
    with pytest.raises(DatasetError, match=r"good.h5: split 'train' not found; available splits: \['test'\]"):
        read_split(good_file, "train")
    with pytest.raises(DatasetError, match=r"/test lacks dataset\(s\) \['velocity'\]"):
        read_split(good_file, "test", ("accel", "velocity"))


def test_window_longer_than_stored(good_file):
    with pytest.raises(DatasetError, match=r"window n_steps = 17 but /test/accel stores 16 steps"):
        read_split(good_file, "test", ("accel", "road"), n_steps=17)
    with pytest.raises(DatasetError, match="n_steps = 0"):
        read_split(good_file, "test", ("accel",), n_steps=0)
    assert read_split(good_file, "test", ("accel",), n_steps=16)["accel"].shape == (4, 16, 3)


@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
def test_non_finite_values(tmp_path, bad):
    arrays = random_split(3, 8)
    arrays["accel"][1, 5, 2] = bad
    path = tmp_path / "nan.h5"
    write_plain(path, {"test": arrays})
    with pytest.raises(DatasetError, match=r"/test/accel contains non-finite values \(first at index \(1, 5, 2\)"):
        read_split(path, "test", ("accel", "road"))
    assert read_split(path, "test", ("road",))["road"].shape == (3, 8)  # other keys still readable
    assert not np.isfinite(read_split(path, "test", ("accel",), check_finite=False)["accel"]).all()


@pytest.mark.parametrize(
    "key,shape,pattern",
    [
        ("accel", (4, 16, 2), r"/test/accel has shape \(4, 16, 2\)"),
        ("accel", (4, 16), r"/test/accel has shape \(4, 16\)"),
        ("road", (4, 16, 3), r"/test/road has shape \(4, 16, 3\)"),
        ("params", (4, 9), r"/test/params has shape \(4, 9\)"),
        ("params", (5, 10), r"/test/params has 5 samples, other keys have 4"),
    ],
)
def test_wrong_shape(tmp_path, key, shape, pattern):
    arrays = {k: v for k, v in random_split(4, 16).items() if k in ("accel", "road", "params")}
    arrays[key] = np.zeros(shape, dtype=arrays[key].dtype)
    path = tmp_path / "shape.h5"
    write_plain(path, {"test": arrays})
    with pytest.raises(DatasetError, match=pattern):
        read_split(path, "test", ("accel", "road", "params"))


def test_split_that_is_not_a_group(tmp_path):
    path = tmp_path / "flat.h5"
    with h5py.File(path, "w") as f:
        f.create_dataset("test", data=np.zeros(3))
    with pytest.raises(DatasetError, match="not a group"):
        read_split(path, "test")


def test_schema_1_files_still_read_and_say_euler_from_rest(tmp_path):
    path = tmp_path / "v1.h5"
    split = random_split(3, 8)
    write_plain(
        path,
        {"test": split},
        attrs={
            "schema": "hybridqcm.dataset/1",
            "h": 0.01,
            "integrator": "semi_explicit_euler",
            "created_by": "hybridqcm 0.1 qcm-simulate (me@here)",
        },
    )
    np.testing.assert_array_equal(read_split(path, "test", ("accel",))["accel"], split["accel"])
    info = dataset_info(path)
    assert (info["physics"], info["initial_state"]) == ("euler", "rest")


def test_a_logger_file_is_continuous_with_unknown_initial_state(tmp_path):
    path = tmp_path / "logger.h5"
    accel = random_split(4, 16)["accel"]
    accel[..., 2] = np.nan  # no wheel accelerometer
    write_plain(path, {"drive": {"accel": accel}}, attrs={"h": 0.002})  # no road, no params, no physics
    info = dataset_info(path)
    assert (info["physics"], info["initial_state"]) == ("continuous", "unknown")
    out = read_split(path, "drive", ("accel",))
    assert out["h"] == 0.002 and np.isnan(out["accel"][..., 2]).all()
    assert recorded_channels(path, "drive") == ["a3", "a2"]
    accel[1, 3, 0] = np.nan  # a gap in a recorded channel is still an error
    write_plain(tmp_path / "gap.h5", {"drive": {"accel": accel}})
    with pytest.raises(
        DatasetError, match=r"gap.h5: /drive/accel contains non-finite values \(first at index \(1, 3, 0\)"
    ):
        read_split(tmp_path / "gap.h5", "drive", ("accel",))


@pytest.mark.parametrize("h,shown", [("0.01", "'0.01'"), (0.0, "0.0"), (-0.01, "-0.01"), (np.inf, "inf")])
def test_attribute_h_must_be_a_positive_number(tmp_path, h, shown):
    path = tmp_path / "h.h5"
    write_plain(path, {"test": random_split(2, 8)}, attrs={"h": h})
    with pytest.raises(DatasetError, match=rf"h.h5: attribute h = {shown} must be a positive number"):
        read_split(path, "test", ("accel",))
    with pytest.raises(DatasetError, match="attribute h"):
        dataset_info(path)


def test_accel_dtype_must_be_floating(tmp_path):
    path = tmp_path / "int.h5"
    write_plain(path, {"test": {"accel": np.zeros((2, 8, 3), np.int16)}})
    with pytest.raises(DatasetError, match=r"int.h5: /test/accel has dtype int16; expected float32 or float64"):
        read_split(path, "test", ("accel",))


def test_schema_2_attributes_and_state0(tmp_path):
    path = tmp_path / "c.h5"
    write_tiny_dataset(path, physics="continuous", warmup_s=(1.0, 4.0), n_steps=64)
    info = dataset_info(path)
    assert info["attrs"]["schema"] == SCHEMA == "hybridqcm.dataset/2"
    assert (info["physics"], info["initial_state"]) == ("continuous", "mid-drive")
    assert info["attrs"]["warmup_s"] == [1.0, 4.0] and info["attrs"]["integrator"] == "exact"
    out = read_split(path, "test", ("state0", "vel", "disp"))
    assert out["state0"].dtype == np.float64 and out["state0"].shape[1] == 6
    np.testing.assert_allclose(
        out["state0"], np.concatenate([out["vel"][:, 0], out["disp"][:, 0]], -1), rtol=1e-6, atol=1e-9
    )


# -- data stored elsewhere (issue 29): before, h5py's KeyError traceback or data read unnoticed ------------
def _linked(path, link):
    with h5py.File(path, "w") as f:
        f.attrs["h"] = 0.01
        f.create_dataset("test/road", data=np.zeros((2, 8), np.float32))
        f["test"]["accel"] = link(path)
    return path


@pytest.mark.parametrize(
    "link, message",
    [
        (
            lambda p: h5py.ExternalLink(str(p.parent / "gone.h5"), "/test/accel"),
            r"gone.h5:/test/accel \(a file that does not exist\)",
        ),
        (lambda p: h5py.ExternalLink(str(p), "/test/accel"), r"\(this file itself: a loop\)"),
        (
            lambda p: h5py.ExternalLink(str(p.parent / "other.h5"), "/test/accel"),
            r"other.h5:/test/accel \(another file, whose changes would not be noticed\)",
        ),
        (lambda p: h5py.SoftLink("/test/nothing"), "soft link to /test/nothing, which leads nowhere or in a loop"),
    ],
)
def test_links_out_of_the_file_or_nowhere_are_one_line(tmp_path, link, message):
    other = tmp_path / "other.h5"
    with h5py.File(other, "w") as f:
        f.create_dataset("test/accel", data=np.ones((2, 8, 3), np.float32))
    path = _linked(tmp_path / "linked.h5", link)
    for read in (dataset_info, lambda p: read_split(p, "test", ("accel",))):
        with pytest.raises(DatasetError, match=rf"linked.h5: /test/accel is an? .*{message}") as info:
            read(path)
        assert "\n" not in str(info.value)


def test_soft_link_loops_and_virtual_datasets_of_other_files_are_refused(tmp_path):
    loop = tmp_path / "loop.h5"
    with h5py.File(loop, "w") as f:
        f["test/accel"] = h5py.SoftLink("/test/other")
        f["test/other"] = h5py.SoftLink("/test/accel")
    with pytest.raises(DatasetError, match="which leads nowhere or in a loop"):
        dataset_info(loop)
    source = tmp_path / "source.h5"
    with h5py.File(source, "w") as f:
        f.create_dataset("test/accel", data=np.ones((2, 8, 3), np.float32))
    virtual = tmp_path / "virtual.h5"
    with h5py.File(virtual, "w") as f:
        layout = h5py.VirtualLayout(shape=(2, 8, 3), dtype="f4")
        layout[:] = h5py.VirtualSource(str(source), "/test/accel", shape=(2, 8, 3))
        f.create_virtual_dataset("test/accel", layout)
    with pytest.raises(DatasetError, match=r"virtual.h5: /test/accel is a virtual dataset mapping .*source.h5"):
        read_split(virtual, "test", ("accel",))
    inside = tmp_path / "inside.h5"  # a soft link within the file is fine
    with h5py.File(inside, "w") as f:
        f.create_dataset("data/accel", data=np.ones((2, 8, 3), np.float32))
        f["test/accel"] = h5py.SoftLink("/data/accel")
    assert read_split(inside, "test", ("accel",))["accel"].shape == (2, 8, 3)


def test_an_unknown_physics_attribute_is_refused(tmp_path):
    path = tmp_path / "quantum.h5"
    with h5py.File(path, "w") as f:
        f.attrs.update(h=0.01, physics="quantum")
        f.create_dataset("test/accel", data=np.ones((2, 8, 3), np.float32))
    with pytest.raises(
        DatasetError, match=r"quantum.h5: attribute physics = 'quantum' is not one of \['continuous', 'euler'\]"
    ):
        dataset_info(path)  # before: read as continuous physics, silently
