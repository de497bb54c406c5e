"""Scan input: PLY/PCD through Open3D, E57 through pye57 (poses), site manifests, masks, bad input."""

import os
import re
import struct
import uuid

import numpy as np
import pye57
import pytest
from pye57 import libe57
from scipy.spatial.transform import Rotation

from ingest.errors import ScanError
from ingest.render.scans import read_cloud, read_e57, read_mask_points, read_scans
from ingest.runtime.o3d import o3d
from sensorbox.sim.appearance import Texture
from sensorbox.sim.scenes import build_scene
from sensorbox.sim.tls import TlsParams, bundle_poses, simulate_scan, write_site


@pytest.fixture(scope="module")
def sim():
    scene = build_scene("indoor", 3)
    params = TlsParams(step_deg=2.0)
    scans = [
        simulate_scan(scene, Texture(3), T, params, f"s{k}")
        for k, T in enumerate(bundle_poses([-2.0, 0.0, 1.4]))
    ]
    return scene, params, scans


@pytest.mark.parametrize("fmt", ["ply", "pcd"])
def test_site_round_trip(tmp_path, sim, fmt):
    scene, params, scans = sim
    manifest = write_site(tmp_path, scene, scans, fmt, params)
    back = read_scans([manifest])
    assert [b.name for b in back] == ["s0", "s1", "s2"]
    for a, b in zip(scans, back, strict=True):
        np.testing.assert_array_equal(b.xyz, a.xyz_scan)  # float32 on disk: bit exact
        np.testing.assert_array_equal(b.rgb, a.rgb)
        np.testing.assert_allclose(b.T_world_scan, a.T_world_scan, atol=1e-12)
        np.testing.assert_array_equal(b.mask_xyz, a.mask_xyz_scan)
        assert b.masked is None
    assert len(back[0].mask_xyz) > 0  # the indoor glass pane is in view of the central scan


def test_bare_pcd_carries_its_pose_and_bare_ply_is_its_own_frame(tmp_path, sim):
    scene, params, scans = sim
    write_site(tmp_path / "pcd", scene, scans[1:2], "pcd", params)
    write_site(tmp_path / "ply", scene, scans[1:2], "ply", params)
    pcd, ply = read_scans([tmp_path / "pcd" / "s1.pcd", tmp_path / "ply" / "s1.ply"])
    assert (pcd.name, ply.name) == ("s1", "s1_2")  # same stem in two folders: made unique
    np.testing.assert_allclose(pcd.T_world_scan, scans[1].T_world_scan, atol=1e-8)
    np.testing.assert_array_equal(ply.T_world_scan, np.eye(4))
    assert (pcd.name, pcd.source) == ("s1", str(tmp_path / "pcd" / "s1.pcd"))


def _cloud(path, xyz, rgb=None, label=None):
    pc = o3d.t.geometry.PointCloud()
    pc.point.positions = o3d.core.Tensor.from_numpy(np.ascontiguousarray(xyz, np.float32))
    if rgb is not None:
        pc.point.colors = o3d.core.Tensor.from_numpy(np.ascontiguousarray(rgb, np.uint8))
    if label is not None:
        pc.point.label = o3d.core.Tensor.from_numpy(np.ascontiguousarray(label.reshape(-1, 1), np.uint8))
    assert o3d.t.io.write_point_cloud(path, pc)


def test_label_field_marks_points_and_invalid_points_are_dropped(tmp_path, caplog):
    """The dropped points were silent (scene.yaml's `points` the only trace): now a warning and a count."""
    xyz = np.random.default_rng(0).normal(size=(100, 3)).astype(np.float32)
    xyz[[5, 6]] = np.nan
    xyz[7] = 0.0
    label = (np.arange(100) % 3 == 0).astype(np.uint8)
    path = tmp_path / "a.ply"
    _cloud(path, xyz, np.full((100, 3), 7, np.uint8), label)
    (scan,) = read_scans([path])
    keep = np.ones(100, bool)
    keep[[5, 6, 7]] = False
    np.testing.assert_array_equal(scan.xyz, xyz[keep])
    np.testing.assert_array_equal(scan.masked, label[keep] != 0)
    assert scan.dropped_points == 3
    assert [r.getMessage() for r in caplog.records if r.levelname == "WARNING"] == [
        f"{path}: dropped 3 of 100 points: 2 not finite (NaN/inf), 1 at the scanner origin (no return)"
    ]
    (unlabelled,) = read_scans([path], mask_label=None)
    assert unlabelled.masked is None


def test_sixteen_bit_ply_colours_keep_their_high_byte(tmp_path):
    """PLY colours stored as uint16 (0..65535) become 8-bit by their high byte, c // 256: full scale is
    255, half scale 128, 256 is 1 and anything under 256 is 0 (not the low byte, which wraps around)."""
    rgb = np.array([[65535, 32768, 256], [255, 511, 0], [40000, 1000, 65280]], np.uint16)
    pc = o3d.t.geometry.PointCloud()
    pc.point.positions = o3d.core.Tensor.from_numpy(np.arange(9, dtype=np.float32).reshape(3, 3) + 1.0)
    pc.point.colors = o3d.core.Tensor.from_numpy(rgb)
    assert o3d.t.io.write_point_cloud(tmp_path / "c.ply", pc)
    (scan,) = read_scans([tmp_path / "c.ply"])
    assert scan.rgb.dtype == np.uint8
    assert scan.rgb.tolist() == [[255, 128, 1], [0, 1, 0], [156, 3, 255]]


def test_a_scan_without_colours_is_refused(tmp_path):
    """A colourless PLY rendered every image a uniform grey 128, rc 0."""
    _cloud(tmp_path / "b.ply", np.ones((10, 3), np.float32))
    with pytest.raises(ScanError) as err:
        read_scans([tmp_path / "b.ply"])
    assert str(err.value) == (
        f"{tmp_path / 'b.ply'}: the scan has no colours; expected per-point colours (PLY red, green, blue; PCD rgb)"
    )
    with pye57.E57(str(tmp_path / "b.e57"), mode="w") as e:
        xyz = np.ones((10, 3))
        e.write_scan_raw({"cartesianX": xyz[:, 0], "cartesianY": xyz[:, 1], "cartesianZ": xyz[:, 2]})
    with pytest.raises(ScanError) as err:
        read_scans([tmp_path / "b.e57"])
    assert str(err.value) == (
        f"{tmp_path / 'b.e57'}: data3D[0]: the scan has no colours; expected per-point colorRed, colorGreen, colorBlue"
    )


def test_a_mask_cloud_needs_no_colours(tmp_path):
    _cloud(tmp_path / "s.ply", np.ones((10, 3), np.float32), np.full((10, 3), 7, np.uint8))
    _cloud(tmp_path / "m.ply", np.full((4, 3), 2.0, np.float32))
    (tmp_path / "site.yaml").write_text("sensorbox_site: 1\nscans:\n- {file: s.ply, mask: m.ply}\n")
    (scan,) = read_scans([tmp_path / "site.yaml"])
    np.testing.assert_array_equal(scan.mask_xyz, np.full((4, 3), 2.0, np.float32))


@pytest.mark.parametrize("header", [b"", b"ply\nformat ascii 1.0\n"])
def test_an_unreadable_ply_prints_only_our_line(tmp_path, capfd, header):
    """Open3D's "[Open3D WARNING] Read PLY failed" (stdout) and RPly's "Unable to read magic number"
    (stderr) came before the error line."""
    path = tmp_path / "e.ply"
    path.write_bytes(header)
    with pytest.raises(ScanError) as err:
        read_scans([path])
    assert str(err.value) == f"{path}: no points (or not a PLY/PCD file Open3D can read)"
    assert capfd.readouterr() == ("", "")


def _write_e57(path, scans):
    with pye57.E57(str(path), mode="w") as e:
        for name, xyz, rgb, q_wxyz, t in scans:
            data = {
                "cartesianX": xyz[:, 0].astype(np.float64),
                "cartesianY": xyz[:, 1].astype(np.float64),
                "cartesianZ": xyz[:, 2].astype(np.float64),
                "colorRed": rgb[:, 0],
                "colorGreen": rgb[:, 1],
                "colorBlue": rgb[:, 2],
            }
            e.write_scan_raw(data, name=name, rotation=np.array(q_wxyz), translation=np.array(t))


def test_e57_two_scans_with_poses(tmp_path):
    rng = np.random.default_rng(4)
    scans = []
    for k in range(2):
        xyz = rng.uniform(-5, 5, (2500, 3)).astype(np.float32)
        rgb = rng.integers(0, 256, (2500, 3)).astype(np.uint8)
        q = Rotation.from_euler("zyx", [30 * (k + 1), 5, -3], degrees=True).as_quat()  # x y z w
        scans.append((f"station {k}", xyz, rgb, [q[3], q[0], q[1], q[2]], [1.0 + k, -2.0, 0.5 * k]))
    path = tmp_path / "site.e57"
    _write_e57(path, scans)
    for chunk in (1000, 1_000_000):  # several reader calls or one
        got = read_e57(path, chunk=chunk)
        assert [g.name for g in got] == ["station 0", "station 1"]
        for (_, xyz, rgb, _, _), g in zip(scans, got, strict=True):
            np.testing.assert_array_equal(g.xyz, xyz)  # pye57 stores single precision
            np.testing.assert_array_equal(g.rgb, rgb)
    # poses: our T_world_scan applied to the local points equals pye57's own global transform
    with pye57.E57(str(path)) as e:
        for k, g in enumerate(read_scans([path])):
            ref = e.read_scan(k, transform=True, ignore_missing_fields=True)
            world = np.stack([ref["cartesianX"], ref["cartesianY"], ref["cartesianZ"]], 1)
            mine = g.xyz.astype(np.float64) @ g.T_world_scan[:3, :3].T + g.T_world_scan[:3, 3]
            np.testing.assert_allclose(mine, world, atol=1e-5)
            np.testing.assert_allclose(g.T_world_scan[:3, 3], scans[k][4])


def _write_spherical_e57(path, r, az, el, rgb):
    """One scan of spherical coordinates (pye57 writes only cartesian ones): libE57's own API, as pye57's
    `write_scan_raw` uses it, with a range/azimuth/elevation prototype in double precision."""
    with pye57.E57(str(path), mode="w") as e:
        f = e.image_file
        scan = libe57.StructureNode(f)
        scan.set("guid", libe57.StringNode(f, f"{{{uuid.uuid4()}}}"))
        scan.set("name", libe57.StringNode(f, "spherical"))
        proto = libe57.StructureNode(f)
        data = {"sphericalRange": r, "sphericalAzimuth": az, "sphericalElevation": el}
        for name in data:
            proto.set(name, libe57.FloatNode(f, 0.0, libe57.E57_DOUBLE))
        for k, name in enumerate(("colorRed", "colorGreen", "colorBlue")):
            proto.set(name, libe57.IntegerNode(f, 0, 0, 255))
            data[name] = rgb[:, k]
        points = libe57.CompressedVectorNode(f, proto, libe57.VectorNode(f, True))
        scan.set("points", points)
        e.data3d.append(scan)
        arrays = {  # colours as int16: the binding refuses int32 buffers (and misreads 64-bit ones)
            n: np.ascontiguousarray(v, np.float64 if n.startswith("sph") else np.int16)
            for n, v in data.items()
        }
        buffers = libe57.VectorSourceDestBuffer()
        for name, a in arrays.items():
            buffers.append(libe57.SourceDestBuffer(f, name, a, len(a), True, False))
        writer = points.writer(buffers)
        writer.write(len(r))
        writer.close()


def test_e57_spherical_coordinates_become_cartesian_points(tmp_path):
    """E57's spherical convention: x = r cos(el) cos(az), y = r cos(el) sin(az), z = r sin(el); a point
    straight up (el = 90 deg) at 2 m is (0, 0, 2), one on the horizon at az = 0 lies on x."""
    r = np.array([2.0, 3.0, 4.0, 1.0])
    az = np.array([0.0, 0.0, np.pi / 2, np.pi])
    el = np.array([np.pi / 2, 0.0, np.pi / 6, -np.pi / 4])
    rgb = np.array([[1, 2, 3], [4, 5, 6], [7, 8, 9], [10, 11, 12]])
    _write_spherical_e57(tmp_path / "s.e57", r, az, el, rgb)
    (scan,) = read_e57(tmp_path / "s.e57")
    half = np.sqrt(0.5)
    want = [[0.0, 0.0, 2.0], [3.0, 0.0, 0.0], [0.0, 4.0 * np.sqrt(0.75), 2.0], [-half, 0.0, -half]]
    np.testing.assert_allclose(scan.xyz, want, atol=1e-6)
    np.testing.assert_array_equal(scan.rgb, rgb)
    assert scan.name == "spherical" and np.array_equal(scan.T_world_scan, np.eye(4))


def test_bad_inputs_name_the_file(tmp_path, sim):
    with pytest.raises(ScanError, match="no such scan"):
        read_scans([tmp_path / "missing.ply"])
    (tmp_path / "x.las").write_bytes(b"LASF")
    with pytest.raises(ScanError, match=r"x\.las.*unknown scan format"):
        read_scans([tmp_path / "x.las"])
    (tmp_path / "bad.yaml").write_text("scans: []\n")
    with pytest.raises(ScanError, match=r"bad\.yaml.*not a site manifest"):
        read_scans([tmp_path / "bad.yaml"])
    scene, params, scans = sim
    manifest = write_site(tmp_path / "site", scene, scans[:1], "ply", params)
    text = manifest.read_text().replace("- - 1.0", "- - 2.0", 1)  # a scaled, non-rigid pose
    manifest.write_text(text)
    with pytest.raises(ScanError, match=r"scans\[0\]\.T_world_scan.*orthonormal"):
        read_scans([manifest])
    (tmp_path / "broken.e57").write_bytes(b"ASTM-E57" + b"\0" * 100)
    with pytest.raises(ScanError, match=r"broken\.e57.*not a readable E57") as err:
        read_scans([tmp_path / "broken.e57"])
    assert "\n" not in str(err.value)  # pye57's text carries libE57's debug report on further lines
    (tmp_path / "empty.ply").write_text("ply\nformat ascii 1.0\nelement vertex 0\nproperty float x\n"
                                        "property float y\nproperty float z\nend_header\n")  # fmt: skip
    with pytest.raises(ScanError, match=r"empty\.ply.*no points"):
        read_scans([tmp_path / "empty.ply"])


def test_pcd_viewpoint_must_have_seven_numbers(tmp_path):
    _cloud(tmp_path / "v.pcd", np.ones((3, 3), np.float32), np.full((3, 3), 7, np.uint8))
    data = (tmp_path / "v.pcd").read_bytes().replace(b"VIEWPOINT 0 0 0 1 0 0 0", b"VIEWPOINT 0 0 0 1")
    (tmp_path / "v.pcd").write_bytes(data)
    with pytest.raises(ScanError, match="VIEWPOINT needs 7 numbers"):
        read_scans([tmp_path / "v.pcd"])


def _crc32c(data: bytes) -> int:
    crc = 0xFFFFFFFF
    for byte in data:
        crc ^= byte
        for _ in range(8):
            crc = (crc >> 1) ^ (0x82F63B78 & -(crc & 1))
    return crc ^ 0xFFFFFFFF


def test_e57_with_invalid_zero_record_data_is_a_scan_error(tmp_path):
    """A well-formed E57 (valid page checksums) whose points section starts with zeros."""
    xyz = np.random.default_rng(1).uniform(-3, 3, (40, 3)).astype(np.float32)
    _write_e57(tmp_path / "ok.e57", [("st", xyz, np.full((40, 3), 9, np.uint8), [1, 0, 0, 0], [0, 0, 0])])
    data = bytearray((tmp_path / "ok.e57").read_bytes())
    found = re.search(rb'<points type="CompressedVector" fileOffset="(\d+)"', data)
    assert found is not None
    offset = int(found.group(1))
    data[offset : offset + 32] = bytes(32)  # the binary section's header: id, lengths, offsets
    for page in range(0, len(data), 1024):  # E57 pages: 1020 bytes + big-endian CRC-32C
        data[page + 1020 : page + 1024] = struct.pack(">I", _crc32c(bytes(data[page : page + 1020])))
    (tmp_path / "zero.e57").write_bytes(data)
    with pytest.raises(ScanError, match=r"zero\.e57: data3D\[0\]: libE57 cannot read it: .*ErrorInternal\)$"):
        read_scans([tmp_path / "zero.e57"])
    assert len(read_scans([tmp_path / "ok.e57"])[0].xyz) == 40  # the same file intact reads


def test_open3d_failures_name_the_file(tmp_path):
    _cloud(tmp_path / "t.ply", np.ones((100, 3), np.float32))
    _cloud(tmp_path / "t.pcd", np.ones((100, 3), np.float32))
    for name in ("t.ply", "t.pcd"):
        data = (tmp_path / name).read_bytes()
        (tmp_path / f"short_{name}").write_bytes(data[: len(data) - 600])
        # Open3D zero-fills a short PLY (the zeros would be dropped as no-returns): caught by the size
        with pytest.raises(ScanError, match=rf"short_{name}: truncated: its header promises \d+ bytes"):
            read_scans([tmp_path / f"short_{name}"])
    (tmp_path / "a.ply").write_bytes(b"ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\n"
                                     b"property float y\nproperty float z\nend_header\n1 2 3\n4 5 6\n")  # fmt: skip
    with pytest.raises(
        ScanError, match=r"a\.ply: truncated: its header declares 3 points, the file has 2 lines"
    ):
        read_scans([tmp_path / "a.ply"])
    # a face element keeps the size check out of it: Open3D's own error, without colours or C++ paths
    (tmp_path / "l.ply").write_bytes(b"ply\nformat binary_little_endian 1.0\nelement vertex 99999999999\n"
                                     b"property float x\nelement face 1\nproperty list uchar int vertex_indices\n"
                                     b"end_header\n")  # fmt: skip
    with pytest.raises(ScanError, match=r"l\.ply: Open3D cannot read it: Total size of property x") as err:
        read_scans([tmp_path / "l.ply"])
    assert "\x1b" not in str(err.value) and ".cpp" not in str(err.value)


@pytest.mark.parametrize(
    ("entry", "problem"),
    [
        ("{name: [1, 2], file: room.ply}", "scans[0].name is [1, 2] (list); expected a non-empty string"),
        ("{file: 3}", "scans[0].file is 3 (int); expected a non-empty string"),
        ("{file: room.ply, mask: {a: 1}}", "scans[0].mask is {'a': 1} (dict); expected a non-empty string"),
        ("{file: ''}", "scans[0].file is '' (str); expected a non-empty string"),
        (
            "{file: room.ply, T_world_scn: [[1]]}",
            "scans[0]: unknown key 'T_world_scn'; expected name, file, T_world_scan, mask",
        ),
    ],
)
def test_site_entry_keys_of_the_wrong_type_name_the_key(tmp_path, entry, problem):
    """A list as a name reached `_unique_names` (TypeError: unhashable type: 'list'), a traceback."""
    manifest = tmp_path / "site.yaml"
    manifest.write_text(f"sensorbox_site: 1\nscans:\n- {entry}\n")
    with pytest.raises(ScanError) as err:
        read_scans([manifest])
    assert str(err.value) == f"{manifest}: {problem}"


def test_an_ascii_pcd_whose_last_line_has_no_newline_is_whole(tmp_path):
    """PCL's test/nhood_test.pcd ends its last point without a newline: it was called truncated
    ('header declares 36 points, the file has 35 lines'). One line short is still named."""
    header = (b"# .PCD v0.7\nVERSION 0.7\nFIELDS x y z rgb\nSIZE 4 4 4 4\nTYPE F F F U\nCOUNT 1 1 1 1\nWIDTH 3\n"
              b"HEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS 3\nDATA ascii\n")  # fmt: skip
    (tmp_path / "whole.pcd").write_bytes(header + b"1 2 3 16711680\n4 5 6 65280\n7 8 9 255")
    xyz = read_scans([tmp_path / "whole.pcd"])[0].xyz
    np.testing.assert_array_equal(np.asarray(xyz), [[1, 2, 3], [4, 5, 6], [7, 8, 9]])
    (tmp_path / "short.pcd").write_bytes(header + b"1 2 3 16711680\n4 5 6 65280")
    with pytest.raises(
        ScanError, match=r"short\.pcd: truncated: its header declares 3 points, the file has 2 lines"
    ):
        read_scans([tmp_path / "short.pcd"])


def test_an_e57_in_a_site_manifest_is_read_with_its_poses_composed(tmp_path):
    """An E57 listed in a site manifest was read as a PLY/PCD ('no points (or not a PLY/PCD file Open3D
    can read)', libE57's bunnyDouble.e57 too): each of its scans now takes the entry's pose composed
    with its own, and the entry's name with an index; an E57 without a scan is named."""
    import yaml

    rng = np.random.default_rng(5)
    scans = []
    for k in range(2):
        xyz = rng.uniform(-5, 5, (500, 3)).astype(np.float32)
        rgb = rng.integers(0, 256, (500, 3)).astype(np.uint8)
        q = Rotation.from_euler("z", 40 * (k + 1), degrees=True).as_quat()
        scans.append((f"s{k}", xyz, rgb, [q[3], q[0], q[1], q[2]], [1.0 + k, 0.0, 0.0]))
    _write_e57(tmp_path / "two.e57", scans)
    T_site = np.eye(4)
    T_site[:3, :3] = Rotation.from_euler("x", 90, degrees=True).as_matrix()
    T_site[:3, 3] = [10.0, 0.0, 0.0]
    site = {
        "sensorbox_site": 1,
        "scans": [{"file": "two.e57", "name": "hall", "T_world_scan": T_site.tolist()}],
    }
    (tmp_path / "site.yaml").write_text(yaml.safe_dump(site))
    got = read_scans([tmp_path / "site.yaml"])
    direct = read_e57(tmp_path / "two.e57")
    assert [g.name for g in got] == ["hall_0", "hall_1"]
    for g, d in zip(got, direct, strict=True):
        np.testing.assert_array_equal(g.xyz, d.xyz)
        np.testing.assert_allclose(g.T_world_scan, T_site @ d.T_world_scan)
    with pye57.E57(str(tmp_path / "empty.e57"), mode="w"):
        pass
    with pytest.raises(ScanError, match=r"empty\.e57: holds no scan \(no data3D section"):
        read_scans([tmp_path / "empty.e57"])


@pytest.mark.parametrize("kind", ["link to /dev/zero", "fifo", "folder"])
def test_a_cloud_path_that_is_no_regular_file_is_one_line_before_a_byte_is_read(tmp_path, kind):
    """render-benchmark --mask /dev/zero read a header without end until a MemoryError traceback; a FIFO
    would wait forever."""
    path = tmp_path / "mask.ply"
    if kind == "fifo":
        os.mkfifo(path)
        what = "a FIFO (named pipe)"
    elif kind == "folder":
        path.mkdir()
        what = "a folder"
    else:
        path.symlink_to("/dev/zero")
        what = "a character device"
    for read in (read_mask_points, lambda p: read_cloud(p, None)):
        with pytest.raises(ScanError) as err:
            read(path)
        assert str(err.value) == f"{path}: is {what}, not a point cloud file"


def test_a_site_naming_two_scans_alike_is_refused(tmp_path):
    """Sweep 5: two scans named s0 in one site.yaml were read, the second silently renamed s0_2 (and
    `--center s0` then chose one of them). Names given in a manifest are the user's: each its own."""
    manifest = tmp_path / "site.yaml"
    manifest.write_text("sensorbox_site: 1\nscans:\n- {name: s0, file: a.ply}\n- {name: s0, file: b.ply}\n")
    with pytest.raises(ScanError) as err:
        read_scans([manifest])
    assert (
        str(err.value)
        == f"{manifest}: scans[1].name 's0' is also scans[0]'s; expected a name of its own for each scan"
    )


def test_a_scan_of_zeros_without_a_header_end_is_refused_after_its_first_mib(tmp_path):
    """Sweep 7 T1: a 20 GiB sparse file of zeros named s0.ply was read whole as its header (MemoryError
    after 71 s). A header that does not end within 1 MiB is refused naming the file."""
    path = tmp_path / "s0.ply"
    with path.open("wb") as f:
        f.truncate(20 << 30)  # sparse: no disk used
    with pytest.raises(ScanError) as err:
        read_scans([path])
    assert str(err.value) == (
        f"{path}: no end of a PLY or PCD header in its first 1 MiB ('end_header' or 'DATA'); expected a point cloud file"
    )
