"""Ingest: photographs of a synthetic object, rendered per pixel, come back as its per-vertex
observations; PNG decoding, sRGB, distortion, masks; the photometric-stereo convention; bad input."""

import json
import os
import shutil
import zlib

import jax.numpy as jnp
import numpy as np
import pytest
import trimesh
from PIL import Image

from data_synth.objects import make_object
from jaxrefl import srgb
from jaxrefl.geometry.raycast import RayCaster
from jaxrefl.geometry.rig import PinholeCamera, observation_geometry
from jaxrefl.outputs import render
from jaxrefl.reflectance import brdf
from jaxrefl.scan.images import read_image, write_png
from jaxrefl.scan.ingest import DISTANT, bilinear, ingest, undistort
from jaxrefl.scan.io import ScanError

from .helpers import plate_over_plane, unit
from .test_cli import assert_one_line_error, jaxrefl

# -- a synthetic capture ------------------------------------------------------------------


def _pixel_radiance(caster, cam, vertices, faces, normals, pd, ps, sigma, light, intensity):
    """Exact Torrance-Sparrow radiance of the surface point behind every pixel `(H, W, 3)`:
    attributes interpolated over the hit face, an Embree shadow ray per pixel; 0 off the object."""
    hits, shape = render.camera_hits(caster, cam)
    h = hits.hit
    interp = lambda a: np.einsum("pk,pk...->p...", hits.barycentric[h], a[faces[hits.face[h]]])  # noqa: E731
    p = hits.points[h]
    n = unit(interp(normals))
    d = light - p
    dist = np.linalg.norm(d, axis=1)
    cos_i, cos_o, theta_r = brdf.shading_geometry(jnp.asarray(n), jnp.asarray(d / dist[:, None]),
                                                  jnp.asarray(unit(cam.center - p)))
    f = brdf.torrance_sparrow(jnp.asarray(interp(pd)), jnp.asarray(interp(ps)),
                              jnp.log(jnp.asarray(interp(sigma))), cos_i, cos_o, theta_r)
    rad = np.asarray(brdf.point_light_radiance(f, intensity, cos_i, jnp.asarray(dist)))
    blocked = caster.segments_blocked(p, caster.face_normals[hits.face[h]], np.broadcast_to(light, p.shape))
    img = np.zeros((len(h), 3))
    img[h] = np.where(blocked[:, None], 0.0, rad)
    return img.reshape(*shape, 3)


def _vertex_radiance(vertices, normals, pd, ps, sigma, cam_pos, lights, intensities):
    """Direct synthesis `(N, M, 3)`: the per-vertex model the estimators assume."""
    g = observation_geometry(vertices, normals, cam_pos, lights)
    f = brdf.torrance_sparrow(jnp.asarray(pd)[:, None], jnp.asarray(ps)[:, None],
                              jnp.log(jnp.asarray(sigma))[:, None], g.cos_i, g.cos_o, g.theta_r)
    rad = brdf.point_light_radiance(f, jnp.asarray(intensities)[None], g.cos_i, g.light_distance)
    return np.asarray(rad), g


def _camera_json(cam):
    return {"K": cam.K.tolist(), "R": cam.R.tolist(), "t": cam.t.tolist(), "width": cam.width,
            "height": cam.height, "dist": cam.dist.tolist()}


@pytest.fixture(scope="module")
def capture(tmp_path_factory):
    """Object A (known pd, ps, sigma) photographed by one 320x240 camera under 4 lights."""
    obj = make_object("A", resolution=24)
    centre = 0.5 * (obj.vertices.min(0) + obj.vertices.max(0))
    cam = PinholeCamera.look_at(centre + [0.1, 0.05, 0.45], centre, fov_deg=32, width=320, height=240)
    lights = centre + np.array([[0.3, 0.3, 0.5], [-0.35, 0.1, 0.4], [0.0, -0.05, 0.6], [0.2, 0.5, 0.1]])
    intensity = np.array([1.0, 2.0, 1.5, 1.0])
    caster = RayCaster(obj.vertices, obj.faces)
    images = [_pixel_radiance(caster, cam, obj.vertices, obj.faces, obj.normals, obj.pd, obj.ps,
                              obj.roughness, light, y) for light, y in zip(lights, intensity)]
    direct, geometry = _vertex_radiance(obj.vertices, obj.normals, obj.pd, obj.ps, obj.roughness, cam.center,
                                        lights, intensity)
    folder = tmp_path_factory.mktemp("capture")
    mesh = trimesh.Trimesh(obj.vertices, obj.faces, vertex_normals=obj.normals, process=False)
    # The true normals go into the file (ingest uses a PLY's normals).
    (folder / "mesh.ply").write_bytes(mesh.export(file_type="ply", vertex_normal=True))
    scale = 0.9 / max(float(i.max()) for i in images)
    for k, img in enumerate(images):  # 16-bit linear PNGs, and light 3 as a .npy float image
        if k == 3:
            np.save(folder / "img3.npy", img * scale)
        else:
            write_png(folder / f"img{k}.png", np.round(img * scale * 65535).astype(np.uint16))
    rig = {"type": "pinhole", "mesh": "mesh.ply", "cameras": [_camera_json(cam)],
           "lights": [{"position": p.tolist(), "intensity": float(y)} for p, y in zip(lights, intensity)],
           "images": [{"file": f"img{k}.{'npy' if k == 3 else 'png'}", "exposure": scale} for k in range(4)],
           "transfer": "linear"}
    (folder / "rig.json").write_text(json.dumps(rig))
    return dict(obj=obj, cam=cam, lights=lights, intensity=intensity, caster=caster, images=images,
                direct=direct, geometry=geometry, folder=folder, rig=rig, scale=scale)


def _clean_samples(c, scan):
    """Samples the ingest kept that are well inside lit, seen regions: every ring neighbour lit
    (no shadow edge near) and the view not grazing (no silhouette near)."""
    f = c["obj"].faces
    n = len(c["obj"].vertices)
    lit = c["caster"].visibility(c["lights"]) & (np.asarray(c["geometry"].cos_i) > 0.2)
    bad_neighbour = np.zeros(lit.shape, bool)
    for a, b in ((0, 1), (1, 2), (2, 0), (1, 0), (2, 1), (0, 2)):
        np.logical_or.at(bad_neighbour, f[:, a], ~lit[f[:, b]])
    assert bad_neighbour.shape == (n, 4)
    return scan.valid & lit & ~bad_neighbour & (np.asarray(c["geometry"].cos_o) > 0.3)


def test_ingest_round_trip_matches_direct_synthesis(capture):
    scan = ingest(capture["folder"])
    assert scan.n_points == len(capture["obj"].vertices) and scan.n_lights == 4
    np.testing.assert_allclose(scan.intensities(), capture["intensity"])
    np.testing.assert_allclose(scan.cam_pos, capture["cam"].center)
    np.testing.assert_allclose(scan.light_pos, capture["lights"])
    assert scan.meta["normals"] == "mesh file"
    np.testing.assert_allclose(scan.normals, capture["obj"].normals, atol=1e-6)  # PLY floats
    # Nothing invisible to the camera is kept.
    facing = np.asarray(capture["geometry"].cos_o[:, 0]) > 0
    seen = capture["caster"].visibility(capture["cam"].center)[:, 0] & facing
    assert not np.any(scan.valid & ~seen[:, None])
    assert 0.25 < scan.valid.mean() < 0.5
    counts = scan.meta["masked_samples"]
    assert counts["mixed_pixels"] > 0 and counts["shadow_edge"] > 0 and counts["saturated"] == 0
    sel = _clean_samples(capture, scan)
    assert sel.sum() > 600
    got, want = scan.radiance[sel].mean(axis=1), capture["direct"][sel].mean(axis=1)
    rel = np.abs(got - want) / want
    # Interpolation error: the shading has a kink at every vertex (normals and albedo are
    # interpolated per face), so the bilinear sample is off by O(pixel / edge) there (measured:
    # median 0.5 %, 90th percentile 4.6 %; it halves with each doubling of the image size). The
    # few worst (up to ~40 %) sit on the coarse beak, where a pixel's interpolated normal turns
    # away from the camera and that pixel is black.
    assert np.median(rel) < 0.01 and np.percentile(rel, 90) < 0.07 and np.percentile(rel, 99) < 0.25
    # Within the interpolation error: no worse than the spread of the four pixels sampled.
    uv, _ = capture["cam"].project(capture["obj"].vertices)
    inside = []
    for j in range(4):
        rows = np.flatnonzero(sel[:, j])
        values, corners, _ = bilinear(capture["images"][j], uv[rows])
        spread = np.abs(capture["images"][j].reshape(-1, 3)[corners] - values[:, None]).max(axis=(1, 2))
        err = np.abs(scan.radiance[rows, j] - capture["direct"][rows, j]).max(axis=1)
        inside.append(err <= spread + 2e-3 * capture["direct"][rows, j].max(axis=1))
    assert np.mean(np.concatenate(inside)) > 0.95


def test_ingest_is_exact_where_the_image_is_smooth(tmp_path):
    """A plate hovering over a plane, seen from above: the plane's Lambertian shading is smooth,
    so every kept sample is exact to bilinear error, unless an occluded, mixed (plate edge) or
    shadow-edge sample slipped through, which would be off by tens of percent."""
    v, f = plate_over_plane(plate_half=0.3, height=0.4)
    pd = np.full((len(v), 3), 0.6)
    zeros = np.zeros(len(v))
    normals = np.tile([0.0, 0.0, 1.0], (len(v), 1))
    cam = PinholeCamera.look_at([0.3, 0.2, 2.5], [0.0, 0.0, 0.0], up=(0.0, 1.0, 0.0), fov_deg=50, width=200,
                                height=200)
    light = np.array([0.8, -0.5, 1.5])
    caster = RayCaster(v, f)
    img = _pixel_radiance(caster, cam, v, f, normals, pd, zeros, np.full(len(v), 0.1), light, 5.0)
    write_png(tmp_path / "img.png", np.round(img / img.max() * 0.9 * 65535).astype(np.uint16))
    trimesh.Trimesh(v, f, process=False).export(tmp_path / "mesh.ply")
    rig = {"mesh": "mesh.ply", "cameras": [_camera_json(cam)],
           "lights": [{"position": light.tolist(), "intensity": 5.0}],
           "images": [{"file": "img.png", "exposure": 0.9 / img.max()}], "transfer": "linear"}
    (tmp_path / "rig.json").write_text(json.dumps(rig))
    scan = ingest(tmp_path)
    direct, _ = _vertex_radiance(v, normals, pd, zeros, np.full(len(v), 0.1), cam.center, light[None], [5.0])
    lit = caster.visibility(light)
    ok = scan.valid[:, 0] & lit[:, 0]
    under = (np.abs(v[:, 0]) < 0.25) & (np.abs(v[:, 1]) < 0.25) & (v[:, 2] == 0)  # hidden by the plate
    assert not np.any(scan.valid[under, 0])
    assert ok.sum() > 1000 and scan.meta["masked_samples"]["mixed_pixels"] > 0
    assert scan.meta["masked_samples"]["shadow_edge"] > 0
    rel = np.abs(scan.radiance[ok, 0] - direct[ok, 0]).max(axis=1) / direct[ok, 0].max(axis=1)
    assert rel.max() < 0.01
    shadowed = scan.valid[:, 0] & ~lit[:, 0]
    assert shadowed.sum() > 50 and scan.radiance[shadowed, 0].max() < 1e-3 * direct[ok, 0].max()


def test_8bit_srgb_photographs_agree_within_quantisation(capture, tmp_path):
    folder = tmp_path / "srgb"
    shutil.copytree(capture["folder"], folder)
    rig = dict(capture["rig"], transfer="srgb")
    for k, img in enumerate(capture["images"]):
        lin = np.clip(img * capture["scale"], 0, 1)
        enc = np.where(lin <= 0.0031308, 12.92 * lin, 1.055 * lin ** (1 / 2.4) - 0.055)
        # Written by Pillow, whose rows use the Sub, Up and Paeth filters.
        Image.fromarray(np.round(enc * 255).astype(np.uint8)).save(folder / f"img{k}.png")
        rig["images"][k] = {"file": f"img{k}.png", "exposure": capture["scale"]}
    (folder / "rig.json").write_text(json.dumps(rig))
    exact, quantised = ingest(capture["folder"]), ingest(folder)
    assert np.array_equal(exact.valid, quantised.valid)
    # Half a code in sRGB moves linear by at most (dlinear/dsrgb) * 0.5 / 255 at each corner pixel.
    lin = exact.radiance * capture["scale"]
    enc = np.where(lin <= 0.0031308, 12.92 * lin, 1.055 * lin ** (1 / 2.4) - 0.055)
    slope = np.where(enc <= 0.04045, 1 / 12.92, 2.4 / 1.055 * ((enc + 0.055) / 1.055) ** 1.4)
    bound = (slope * 0.5 / 255 + 2e-3 * lin + 1e-5) / capture["scale"]
    v = exact.valid
    assert np.all(np.abs(quantised.radiance - exact.radiance)[v] <= bound[v])
    assert np.abs(quantised.radiance - exact.radiance)[v].max() > 0  # the quantisation is really there


def test_saturated_pixels_are_masked(capture, tmp_path):
    folder = tmp_path / "sat"
    shutil.copytree(capture["folder"], folder)
    rig = json.loads((folder / "rig.json").read_text())
    gain = 6 * capture["scale"]
    for k, img in enumerate(capture["images"][:3]):  # over-exposed 16-bit images clip the highlights
        write_png(folder / f"img{k}.png", np.round(np.clip(img * gain, 0, 1) * 65535).astype(np.uint16))
        rig["images"][k]["exposure"] = gain
    (folder / "rig.json").write_text(json.dumps(rig))
    scan, exact = ingest(folder), ingest(capture["folder"])
    assert scan.meta["masked_samples"]["saturated"] > 20
    assert np.all(scan.valid <= exact.valid) and scan.valid.sum() < exact.valid.sum()
    v = scan.valid
    np.testing.assert_allclose(scan.radiance[v], exact.radiance[v], rtol=1e-3, atol=2e-5 / capture["scale"])
    # The dropped samples are exactly those whose bilinear pixels include a clipped one.
    uv, _ = capture["cam"].project(capture["obj"].vertices)
    for j in range(3):
        rows = np.flatnonzero(exact.valid[:, j])
        _, corners, weights = bilinear(capture["images"][j], uv[rows])
        clipped = capture["images"][j].reshape(-1, 3)[corners].max(axis=-1) * gain >= 1.0 - 0.5 / 65535
        np.testing.assert_array_equal(np.any(clipped & (weights > 1e-9), axis=1), ~v[rows, j])


# -- pieces --------------------------------------------------------------------------------


def _encode_png(img, filters):
    """An 8/16-bit PNG with the given per-row filter types (the filters computed here, vectorised)."""
    h, w, ch = img.shape
    depth = 16 if img.dtype == np.uint16 else 8
    bpp = ch * depth // 8
    x = np.ascontiguousarray(img.astype(">u2" if depth == 16 else np.uint8)).view(np.uint8)
    x = x.reshape(h, w * bpp)
    x = x.astype(np.int32)
    left = np.concatenate([np.zeros((h, bpp), np.int32), x[:, :-bpp]], axis=1)
    up = np.concatenate([np.zeros((1, w * bpp), np.int32), x[:-1]], axis=0)
    ul = np.concatenate([np.zeros((h, bpp), np.int32), up[:, :-bpp]], axis=1)
    p = left + up - ul
    pa, pb, pc = np.abs(p - left), np.abs(p - up), np.abs(p - ul)
    paeth = np.where((pa <= pb) & (pa <= pc), left, np.where(pb <= pc, up, ul))
    preds = np.stack([np.zeros_like(x), left, up, (left + up) // 2, paeth])
    rows = (x - preds[filters, np.arange(h)]) & 255
    raw = np.concatenate([filters[:, None], rows], axis=1).astype(np.uint8).tobytes()
    import struct

    def chunk(kind, data):
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))

    ctype = {1: 0, 2: 4, 3: 2, 4: 6}[ch]
    return (b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", w, h, depth, ctype, 0, 0, 0))
            + chunk(b"IDAT", zlib.compress(raw)) + chunk(b"IEND", b""))


@pytest.mark.parametrize("dtype, channels", [(np.uint8, 3), (np.uint16, 3), (np.uint16, 1), (np.uint16, 4)])
def test_png_decoder_handles_every_row_filter(tmp_path, dtype, channels):
    rng = np.random.default_rng(3)
    top = np.iinfo(dtype).max
    yy, xx = np.mgrid[0:37, 0:53]
    noise = rng.integers(0, 5000, (37, 53, channels))
    img = (np.stack([xx * 900 + yy * 300] * channels, -1) + noise) % (top + 1)
    img = img.astype(dtype)
    filters = np.arange(37) % 5
    path = tmp_path / "f.png"
    path.write_bytes(_encode_png(img, filters))
    values, full = read_image(path)
    assert full == top
    np.testing.assert_array_equal(np.round(values * top).astype(dtype), img)


def test_png_writer_round_trips_and_pillow_agrees(tmp_path):
    rng = np.random.default_rng(4)
    rgb16 = rng.integers(0, 65536, (20, 30, 3)).astype(np.uint16)
    write_png(tmp_path / "a.png", rgb16)
    values, top = read_image(tmp_path / "a.png")
    assert top == 65535 and np.array_equal(np.round(values * 65535).astype(np.uint16), rgb16)
    grey = rgb16[..., 0]
    write_png(tmp_path / "g.png", grey)
    # Pillow reads 16-bit grey exactly.
    assert np.array_equal(np.asarray(Image.open(tmp_path / "g.png")), grey)
    rgb8 = (rgb16 >> 8).astype(np.uint8)
    Image.fromarray(rgb8).save(tmp_path / "p.png")
    values, top = read_image(tmp_path / "p.png")
    assert top == 255 and np.array_equal(np.round(values * 255).astype(np.uint8), rgb8)
    Image.fromarray(rgb8[..., 0]).convert("P").save(tmp_path / "pal.png")  # palette: as RGB
    assert read_image(tmp_path / "pal.png")[0].shape == (20, 30, 3)
    with pytest.raises(ValueError, match="uint8 or uint16"):
        write_png(tmp_path / "x.png", rgb16.astype(np.float32))


def test_16bit_rgb_png_keeps_every_bit(tmp_path):
    """Pillow and imageio read 16-bit colour PNGs as 8 bits; ours must keep all 16."""
    codes = np.array([0, 1, 255, 256, 257, 4095, 32767, 32768, 65279, 65534, 65535], np.uint16)
    rgb16 = np.stack([codes, codes[::-1], np.roll(codes, 3)], -1).reshape(1, -1, 3).repeat(4, 0)
    rgb16[1::2] ^= 0x00FF  # flip low bytes on alternate rows: lost to any 8-bit path
    write_png(tmp_path / "a.png", rgb16)
    header = (tmp_path / "a.png").read_bytes()[:29]
    assert header[12:16] == b"IHDR" and header[24:26] == bytes([16, 2])  # 16-bit, colour type RGB
    values, top = read_image(tmp_path / "a.png")
    assert top == 65535 and values.shape == rgb16.shape
    np.testing.assert_array_equal(values * 65535, rgb16.astype(np.float64))
    (tmp_path / "bad.png").write_bytes(header + b"\0" * 20)
    with pytest.raises(ValueError, match="corrupt PNG"):
        read_image(tmp_path / "bad.png")


def test_srgb_curve_known_values_and_round_trip():
    np.testing.assert_allclose(srgb.to_linear([0.0, 0.04045, 0.5, 1.0]),
                               [0.0, 0.04045 / 12.92, 0.21404114, 1.0], rtol=1e-6)
    np.testing.assert_allclose(srgb.from_linear([0.0, 0.0031308, 0.21404114, 1.0, 2.0, -1.0]),
                               [0.0, 0.0031308 * 12.92, 0.5, 1.0, 1.0, 0.0], rtol=1e-6)
    # The two pieces meet at the knee (continuous to 1e-7 either side), any shape goes through.
    knee = srgb.to_linear([0.04045 - 1e-12, 0.04045 + 1e-12])
    assert abs(knee[1] - knee[0]) < 1e-7
    x = np.random.default_rng(6).uniform(0, 1, (4, 5, 3))
    assert srgb.to_linear(x).shape == x.shape
    np.testing.assert_allclose(srgb.from_linear(srgb.to_linear(x)), x, atol=1e-12)
    codes = np.arange(256, dtype=np.uint8)
    np.testing.assert_array_equal(srgb.from_linear8(srgb.to_linear(codes / 255)), codes)


def test_undistortion():
    cam = PinholeCamera.look_at([0.1, 0.2, 1.0], [0.0, 0.0, 0.0], width=400, height=300, fov_deg=50)
    cam = PinholeCamera(K=cam.K, R=cam.R, t=cam.t, width=400, height=300,
                        dist=np.array([-0.25, 0.08, 0.001, -0.002, -0.01]))
    rng = np.random.default_rng(5)
    pts = rng.uniform(-0.2, 0.2, (200, 3))
    uv, _ = cam.project(pts)
    d = undistort(cam, uv)
    np.testing.assert_allclose(d, unit(pts - cam.center), atol=1e-9)


# -- photometric stereo ----------------------------------------------------------------------


def test_photometric_stereo_lambertian_normal_map_gives_pd_back(tmp_path):
    h, w = 40, 56
    r, c = np.mgrid[0:h, 0:w]
    x, y = (c - (w - 1) / 2) / 18.0, -(r - (h - 1) / 2) / 18.0
    mask = x**2 + y**2 < 1.0
    n = np.stack([x, y, np.sqrt(np.clip(1 - x**2 - y**2, 0, 1))], -1) * mask[..., None]  # a hemisphere
    pd = np.stack([0.3 + 0.5 * c / w, 0.2 + 0.6 * r / h, np.full((h, w), 0.5)], -1)
    dirs = unit(np.array([[0.3, 0.2, 1], [-0.4, 0.1, 1], [0.1, -0.5, 1], [0.6, 0.5, 0.8], [-0.2, -0.3, 1.0]]))
    rgb = np.array([[1.0, 0.9, 0.8], [0.7, 0.8, 1.0], [1.2, 1.0, 1.1], [0.9, 0.9, 0.9], [1.0, 1.1, 0.9]])
    images = [pd / np.pi * rgb[k] * np.maximum(n @ dirs[k], 0)[..., None] for k in range(len(dirs))]
    scale = 0.95 / max(i.max() for i in images)
    for k, img in enumerate(images):
        write_png(tmp_path / f"im{k}.png", np.round(img * scale * 65535).astype(np.uint16))
    write_png(tmp_path / "normals.png", np.round((n + 1) / 2 * 65535).astype(np.uint16))  # a PNG normal map
    write_png(tmp_path / "mask.png", (mask * 255).astype(np.uint8))
    rig = {"type": "photometric-stereo", "normals": "normals.png", "mask": "mask.png", "pixel_size": 0.002,
           "lights": [{"direction": d.tolist(), "intensity": i.tolist()} for d, i in zip(dirs, rgb)],
           "images": [{"file": f"im{k}.png", "exposure": scale} for k in range(len(dirs))],
           "transfer": "linear"}
    (tmp_path / "rig.json").write_text(json.dumps(rig))
    scan = ingest(tmp_path)
    assert scan.n_points == mask.sum() and np.all(scan.vertices[:, 2] == 0)
    # Pixel (r, c) is the vertex at x = (c - (W-1)/2) size, y = -(r - (H-1)/2) size.
    np.testing.assert_allclose(scan.vertices[:, 0] / 0.002 + (w - 1) / 2, c[mask], atol=1e-9)
    g = observation_geometry(scan.vertices, scan.normals, scan.cam_pos, scan.light_pos)
    # A distant light of intensity I: the bundle's point light gives irradiance I cos to ~1e-6 I
    # (distance: relative 2 extent / D; direction: cos off by at most extent / D).
    irradiance = scan.intensities()[None] * np.asarray(g.cos_i) / np.asarray(g.light_distance) ** 2
    exact = np.maximum(scan.normals @ dirs.T, 0) * rgb.mean(axis=1)[None]
    np.testing.assert_allclose(np.where(np.asarray(g.cos_i) > 0, irradiance, 0), exact, rtol=3e-6, atol=1e-6)
    np.testing.assert_allclose(np.asarray(g.cos_o), scan.normals[:, 2:3] * np.ones((1, 5)), atol=1e-6)
    assert np.allclose(np.linalg.norm(scan.light_pos, axis=1), DISTANT * 0.002 * w)
    e = np.where(scan.valid, np.maximum(irradiance, 0), 0.0)
    ok = np.sum(e > 0, axis=1) >= 3
    pd_hat = np.pi * np.einsum("nm,nmc->nc", e, scan.radiance) / np.sum(e**2, axis=1)[:, None]
    np.testing.assert_allclose(pd_hat[ok], pd[mask][ok], rtol=2e-3)
    assert ok.mean() > 0.9


# -- bad input --------------------------------------------------------------------------------


def _broken(capture, tmp_path, edit):
    folder = tmp_path / "broken"
    shutil.copytree(capture["folder"], folder)
    rig = json.loads((folder / "rig.json").read_text())
    edit(folder, rig)
    (folder / "rig.json").write_text(json.dumps(rig))
    return folder


BAD_CAPTURES = [
    ("images[1]", "not found", lambda f, r: os.remove(f / "img1.png")),
    ("images[2]", "160x120 pixels, its camera is 320x240",
     lambda f, r: write_png(f / "img2.png", np.zeros((120, 160, 3), np.uint16))),
    ("images", "3 image(s) for 4 light(s)", lambda f, r: r["images"].pop()),
    ("images", "light(s) [3] have no image",
     lambda f, r: [e.update(light=min(k, 2)) for k, e in enumerate(r["images"])]),
    ("images[0].light", "index in [0, 3]", lambda f, r: r["images"][0].update(light=9)),
    ("cameras[0].K", "shape (3, 3)", lambda f, r: r["cameras"][0].update(K=[[1, 0], [0, 1]])),
    ("lights[2].position", "shape (3,)", lambda f, r: r["lights"][2].update(position=[0, 1])),
    ("lights[0].intensity", "> 0", lambda f, r: r["lights"][0].update(intensity=-1)),
    ("mesh", "not found", lambda f, r: os.remove(f / "mesh.ply")),
    ("transfer", "'srgb' or 'linear'", lambda f, r: r.update(transfer="gamma")),
    ("images[3]", "non-finite", lambda f, r: np.save(f / "img3.npy", np.full((240, 320, 3), np.nan))),
]


@pytest.mark.parametrize("field, message, edit", BAD_CAPTURES,
                         ids=[b[0] + ":" + b[1][:12] for b in BAD_CAPTURES])
def test_bad_capture_folders_name_the_field(capture, tmp_path, field, message, edit):
    folder = _broken(capture, tmp_path, edit)
    with pytest.raises(ScanError) as info:
        ingest(folder)
    assert info.value.field == field and message in str(info.value)


def test_missing_rig_file_and_bad_json(tmp_path):
    with pytest.raises(ScanError, match="rig.json: missing"):
        ingest(tmp_path)
    (tmp_path / "rig.json").write_text("{not json")
    with pytest.raises(ScanError, match="not valid JSON"):
        ingest(tmp_path)


def test_cli_ingest_and_its_errors(capture, tmp_path):
    out = tmp_path / "scan.npz"
    r = jaxrefl("ingest", capture["folder"], "--out", out, "--json")
    assert r.returncode == 0, r.stderr
    report = json.loads(r.stdout)
    assert report["points"] == len(capture["obj"].vertices) and report["observations"] == 4
    r = jaxrefl("info", out, "--json")
    assert r.returncode == 0 and json.loads(r.stdout)["has_radiance"]
    folder = _broken(capture, tmp_path, lambda f, rig: os.remove(f / "img1.png"))
    bad_out = tmp_path / "never.npz"
    r = jaxrefl("ingest", folder, "--out", bad_out)
    assert_one_line_error(r, "images[1]")
    assert r.stderr.startswith("jaxrefl ingest: error: images[1]: file img1.png not found")
    assert not bad_out.exists() and not any(p.name.startswith(".tmp-") for p in tmp_path.iterdir())
