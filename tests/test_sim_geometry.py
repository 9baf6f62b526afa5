"""The simulator's geometry is exact: world points land where the pinhole model says, depth is true depth.

Checked three ways: (1) facade corners of the tiny world, projected with a written run's truth pose
and camera, coincide (<= 1 px) with the region the renderer drew for that facade; (2) a checkerboard
texture rendered on a quad has its inner corners where their 3-D positions project (sub-pixel: this
catches half-texel mistakes in the texture mapping); (3) the depth buffer back-projects onto the
drawn surfaces.
"""
import cv2
import numpy as np
import pytest

from scenesig.surveys.geometry import Camera, invert, rot_y, transform
from scenesig.surveys.run import read_run
from scenesig.surveys.sim.render import Renderer, build_pyramid, quad_texture_maps
from scenesig.surveys.sim.scene import RunScene, render_view, static_depth
from scenesig.surveys.sim.simulate import simulate
from scenesig.surveys.sim.world import World


@pytest.fixture(scope="module")
def tiny_run(tmp_path_factory):
    out = tmp_path_factory.mktemp("sim_geom")
    simulate(out, preset="tiny", seed=3, runs=["sunny"], camera_hz=4.0, show_progress=False)
    return out, read_run(out / "run00_sunny"), World.load(out / "world.json")


def _polygon_distance(px, poly):
    """Signed distance (px) of points to a convex polygon boundary: >0 inside, <0 outside."""
    c = poly.mean(0)
    d = np.full(len(px), np.inf)
    for k in range(len(poly)):
        a, b = poly[k], poly[(k + 1) % len(poly)]
        n = np.array([a[1] - b[1], b[0] - a[0]])
        n /= np.linalg.norm(n)
        if np.dot(c - a, n) < 0:
            n = -n
        d = np.minimum(d, (px - a) @ n)
    return d


def test_facade_corners_land_where_the_renderer_drew_them(tiny_run):
    out, run, world = tiny_run
    scene = RunScene(world, "sunny", run_key=(0,), camera=run.camera)
    cam = run.camera
    yy, xx = np.mgrid[0:cam.height, 0:cam.width]
    pix = np.stack([xx.ravel(), yy.ravel()], 1).astype(float)
    checked_corners = 0
    checked_quads = 0
    for k in range(0, len(run), 3):
        T_wc = run.truth_poses[k] @ run.T_vehicle_camera  # truth.tum is written at the frame times
        assert np.allclose(run.truth_times[k], run.frame_times[k])
        _, depth, buf = scene.render(T_wc, frame=k, buffers=True)
        ids = buf["ids"].ravel()
        T_cw = invert(T_wc)
        for b in world.buildings:
            qi = b["front_quad"]
            C = transform(T_cw, np.array(b["front"]))
            if np.any(C[:, 2] < 1.0):
                continue
            uv, _ = cam.project(C)
            # plane depth at every pixel: rays meet the facade plane
            n = np.cross(C[1] - C[0], C[3] - C[0])
            n /= np.linalg.norm(n)
            rays = cam.rays(pix)
            z_plane = np.dot(C[0], n) / (rays @ n)
            sd = _polygon_distance(pix, uv)
            inside = sd > 1.0
            outside = sd < -1.0
            drawn = ids == qi
            # nothing of this facade is drawn more than 1 px outside its projected outline
            assert not np.any(drawn & outside), f"facade {qi} drawn outside its projection (frame {k})"
            # inside, every pixel shows the facade unless something nearer hides it
            nearer = depth.ravel() < z_plane * (1 - 1e-4)
            bad = inside & ~drawn & ~nearer
            assert not np.any(bad), f"facade {qi}: {bad.sum()} pixels inside not drawn and not occluded"
            if (inside & drawn).sum() > 50:
                checked_quads += 1
                # drawn pixels have the plane's depth
                assert np.allclose(depth.ravel()[drawn], z_plane[drawn], rtol=1e-4)
            # each visible, unoccluded corner: a pixel of this facade lies within 1 px of it
            for c_uv, c_cam in zip(uv, C):
                if not cam.in_image(c_uv[None], margin=3)[0]:
                    continue
                near_px = np.linalg.norm(pix - c_uv, axis=1) <= 3.0
                if np.any(near_px & nearer):
                    continue  # occluded near the corner
                dmin = np.linalg.norm(pix[drawn & near_px] - c_uv, axis=1).min() if np.any(drawn & near_px) else 9
                assert dmin <= 1.0, f"corner of facade {qi} at {c_uv} but nearest drawn pixel {dmin:.2f} px away"
                checked_corners += 1
    assert checked_quads >= 5 and checked_corners >= 5, (checked_quads, checked_corners)


@pytest.mark.parametrize("sq", [8, 64, 128])  # texels per square: drawn at mip levels 0, 1 and 2
def test_checkerboard_texture_registers_to_subpixel(sq):
    cam = Camera(500.0, 500.0, 319.5, 239.5, 640, 480)
    ii, jj = np.indices((6, 8))
    cells = ((ii + jj) % 2).astype(np.uint8) * 255
    tex = np.repeat(np.repeat(cells, sq, 0), sq, 1)
    tex = np.pad(tex, sq, constant_values=255)  # white border so the detector sees the board
    bgra = np.dstack([tex, tex, tex, np.full_like(tex, 255)])
    W, H = 2.0, 1.6  # metres (board + border)
    # quad in front of the camera (camera frame = world frame here), turned 20 deg about the vertical
    R = rot_y(np.radians(20))
    centre = np.array([0.1, -0.05, 3.0])
    a = R @ np.array([W, 0, 0])
    bvec = R @ np.array([0, H, 0])
    TL = centre - a / 2 - bvec / 2
    corners = np.array([TL, TL + a, TL + a + bvec, TL + bvec])
    r = Renderer(cam)
    r.begin()
    r.draw(np.eye(4), corners[None], quad_texture_maps(corners[None]), lambda i: build_pyramid(bgra),
           np.zeros(1, np.uint8))
    img = r.fb[..., 0].copy()
    ok, det = cv2.findChessboardCornersSB(img, (7, 5), flags=cv2.CALIB_CB_ACCURACY)
    assert ok, "checkerboard not found in the render"
    det = det.reshape(-1, 2)
    # inner corners in texture pixels (edges of texels): x = sq * (1 + i), y = sq * (1 + j) from the padded
    # corner, i.e. at normalised texture coordinates u = x / width
    tw, th = tex.shape[1], tex.shape[0]
    pts = []
    for j in range(1, 6):
        for i in range(1, 8):
            u, v = (sq + i * sq) / tw, (sq + j * sq) / th
            pts.append(TL + a * u + bvec * v)
    uv, _ = cam.project(np.array(pts))
    # match each detection to the nearest prediction (detector order may be reversed)
    d = np.linalg.norm(det[:, None] - uv[None], axis=2).min(1)
    assert d.max() < 0.15, f"texture misregistered by up to {d.max():.3f} px"


def test_depth_buffer_is_true_depth_under_near_plane_clipping():
    """A ground quad passing under the camera (clipped at the near plane) gets exact depth."""
    cam = Camera(250.0, 250.0, 159.5, 119.5, 320, 240)
    tex = np.full((64, 64, 4), 200, np.uint8)
    # camera 1.5 m above a ground plane that extends behind it (camera frame: y down, z forward)
    corners = np.array([[-5, 1.5, 30.0], [5, 1.5, 30.0], [5, 1.5, -5.0], [-5, 1.5, -5.0]])
    r = Renderer(cam)
    r.begin()
    r.draw(np.eye(4), corners[None], quad_texture_maps(corners[None]), lambda i: build_pyramid(tex),
           np.zeros(1, np.uint8))
    depth = r.depth()
    v = np.arange(cam.height)
    rows = v > cam.cy + 250 * 1.5 / 30 + 1  # below the far edge's image row
    expect = 1.5 * cam.fy / (v[rows] - cam.cy)
    got = depth[rows, cam.width // 2]
    assert np.all(np.isfinite(got))
    assert np.allclose(got, expect, rtol=1e-4)
    assert np.all(~np.isfinite(depth[: int(cam.cy), :]))  # nothing above the horizon


def test_world_depth_is_the_static_structure(tiny_run):
    out, run, world = tiny_run
    T_wc = run.truth_poses[len(run) // 2] @ run.T_vehicle_camera
    static = static_depth(world, T_wc, camera=run.camera)
    _, with_run = render_view(world, T_wc, "sunny", run_key=(0,), camera=run.camera)
    fin = np.isfinite(static)
    assert fin.mean() > 0.3
    # the run's parked cars and pedestrians can only hide the structure, never push it back
    assert np.all(with_run[fin] <= static[fin] * (1 + 1e-4))
    assert np.mean(np.isclose(with_run[fin], static[fin], rtol=1e-4)) > 0.8


def test_truth_depth_image_of_a_written_run(tiny_run):
    from scenesig.surveys.sim.truth import depth_image

    out, run, world = tiny_run
    k = len(run) // 3
    d = depth_image(run, k)
    # the same depth the simulator's own scene renders from the truth pose
    scene = RunScene(world, "sunny", run_key=(0,), camera=run.camera)
    _, ref = scene.render(run.truth_poses[k] @ run.T_vehicle_camera, frame=k)
    assert d.shape == (run.camera.height, run.camera.width)
    assert np.array_equal(np.isfinite(d), np.isfinite(ref))
    assert np.allclose(d[np.isfinite(d)], ref[np.isfinite(ref)])
    # the road right in front of the vehicle is about camera height / tan(ray angle) away
    v = run.camera.height - 1
    expected = 1.5 * run.camera.fy / (v - run.camera.cy) / np.cos(np.radians(2.0)) ** 2
    assert abs(d[v, run.camera.width // 2] - expected) / expected < 0.1
    # real runs have no depth truth
    import dataclasses

    real = dataclasses.replace(run, metadata={k_: v for k_, v in run.metadata.items() if k_ != "simulator"})
    assert depth_image(real, k) is None
