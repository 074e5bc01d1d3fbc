"""YCB asset pipeline: processed meshes, inertia, cache, errors, and the MJCF sub-model in MuJoCo.

Reads the models from `$BULBJAX_YCB_DIR`, else `../shared/ycb` next to the repo; writes only to a
temporary cache folder. The Warp texture check compiles render kernels (slow on CPU): it runs
when BULBJAX_RENDER_TESTS=1.
"""

from __future__ import annotations

import io
import os
import time
from pathlib import Path

import mujoco
import numpy as np
import pytest
import trimesh
from PIL import Image

from bulbjax.assets import YCB_DIR_ENV, YCB_INFO, load_ycb_object, ycb_dir, ycb_mjcf
from bulbjax.assets.mesh import uv_stretch
from bulbjax.assets.mjcf import COLLISION_GROUP, _mjcf

REPO = Path(__file__).resolve().parents[1]
# a box without texture (mesh inertia), a can (not closed: hull inertia), two textured fruit
OBJECTS = ["004_sugar_box", "007_tuna_fish_can", "013_apple", "016_pear"]


@pytest.fixture(scope="module")
def ycb_root() -> Path:
    path = Path(os.environ.get(YCB_DIR_ENV) or REPO.parent / "shared" / "ycb")
    if not (path / "013_apple").is_dir():
        pytest.skip(f"YCB models not found at {path} (set {YCB_DIR_ENV})")
    return path


@pytest.fixture(scope="module")
def cache(tmp_path_factory) -> Path:
    return tmp_path_factory.mktemp("ycb_cache")


@pytest.fixture(scope="module")
def built(ycb_root, cache) -> dict:
    out = {}
    for name in OBJECTS:
        t = time.perf_counter()
        out[name] = load_ycb_object(name, ycb_dir=ycb_root, cache_dir=cache)
        print(f"{name}: built in {time.perf_counter() - t:.2f} s")
    return out


def _source_mesh(ycb_root: Path, name: str) -> trimesh.Trimesh:
    return trimesh.load(ycb_root / name / "google_16k" / "textured.obj", process=False,
                        skip_materials=True)


@pytest.mark.parametrize("name", OBJECTS)
def test_meshes_and_inertia(built, ycb_root, name):
    a = built[name]
    assert not a.from_cache
    # visual: decimated (not destroyed), valid indices, UVs carried over without stretching
    assert 1000 <= len(a.visual_faces) <= 2000
    assert a.visual_faces.min() >= 0 and a.visual_faces.max() < len(a.visual_vertices)
    assert a.visual_uv.shape == (len(a.visual_vertices), 2)
    assert a.visual_uv.min() > -0.05 and a.visual_uv.max() < 1.05
    src = _source_mesh(ycb_root, name)
    s = np.asarray(YCB_INFO[name].scale)
    ref = np.median(uv_stretch(np.asarray(src.vertices) * s, np.asarray(src.faces), src.visual.uv))
    stretch = uv_stretch(a.visual_vertices, a.visual_faces, a.visual_uv)
    assert 0.8 < np.median(stretch) / ref < 1.25
    assert np.mean(stretch > 5 * ref) < 0.01  # faces smeared across the texture atlas
    # frame: the file's own, scaled by bulb's s
    np.testing.assert_allclose(a.bounds, np.asarray(src.bounds) * s, atol=1e-9)
    np.testing.assert_allclose(a.visual_vertices.min(0), a.bounds[0], atol=3e-3)
    np.testing.assert_allclose(a.visual_vertices.max(0), a.bounds[1], atol=3e-3)
    # collision: a closed convex hull of a few hundred faces around the object
    hull = trimesh.Trimesh(a.collision_vertices, a.collision_faces)
    assert len(a.collision_faces) <= 200
    assert hull.is_watertight and hull.is_convex and hull.volume > 0
    np.testing.assert_allclose(hull.bounds, a.bounds, atol=4e-3)
    # mass and inertia: bulb's mass, a physical inertia tensor about a COM inside the object
    assert a.mass == YCB_INFO[name].mass
    np.testing.assert_allclose(a.inertia, a.inertia.T)
    ev = np.linalg.eigvalsh(a.inertia)
    assert ev.min() > 0 and ev[2] <= ev[0] + ev[1] + 1e-12
    assert np.all(a.com > a.bounds[0]) and np.all(a.com < a.bounds[1])
    inside = np.einsum("ij,ij->i", hull.face_normals, a.com - hull.triangles[:, 0])
    assert np.all(inside < 0)  # COM inside the (convex) hull: behind every face
    # a box's inertia about its COM, order of magnitude: m (a^2 + b^2) / 3 with half extents
    h = a.half_extents
    box = a.mass / 3 * np.array([h[1]**2 + h[2]**2, h[0]**2 + h[2]**2, h[0]**2 + h[1]**2])
    assert np.all(np.diag(a.inertia) < 1.05 * box) and np.all(np.diag(a.inertia) > 0.2 * box)


def test_texture_or_flat_colour(built):
    box, apple = built["004_sugar_box"], built["013_apple"]
    assert box.texture_path is None and box.rgba == (*YCB_INFO["004_sugar_box"].rgb, 1.0)
    assert apple.texture_path is not None and apple.rgba == (1.0, 1.0, 1.0, 1.0)
    img = Image.open(apple.texture_path)
    assert img.size == (256, 256) and img.mode == "RGB"
    r, g, b = apple.texture_mean_rgb
    assert r > 0.4 and r > 2 * g and r > 2 * b  # a red apple


def test_cache_hit_and_miss(built, ycb_root, cache):
    first = built["013_apple"]
    t = time.perf_counter()
    again = load_ycb_object("013_apple", ycb_dir=ycb_root, cache_dir=cache)
    hit_s = time.perf_counter() - t
    print(f"cache hit: {hit_s * 1000:.1f} ms")
    assert again.from_cache and again.cache_path == first.cache_path
    for field in ("visual_vertices", "visual_faces", "visual_uv", "collision_vertices",
                  "collision_faces", "com", "inertia", "bounds"):
        assert np.array_equal(getattr(again, field), getattr(first, field)), field
    assert again.rgba == first.rgba and again.texture_mean_rgb == first.texture_mean_rgb
    # a changed setting is a different entry
    small = load_ycb_object("004_sugar_box", ycb_dir=ycb_root, cache_dir=cache, max_faces=500)
    assert not small.from_cache and len(small.visual_faces) <= 500
    assert small.cache_path != built["004_sugar_box"].cache_path
    big = load_ycb_object("004_sugar_box", scale=2.0, ycb_dir=ycb_root, cache_dir=cache, max_faces=500)
    assert not big.from_cache and big.cache_path != small.cache_path
    np.testing.assert_allclose(big.bounds, 2 * small.bounds)
    np.testing.assert_allclose(big.inertia, 4 * small.inertia, rtol=1e-9)  # same mass, 2x size
    # only finished entries in the cache (no temporary folders left), nothing else written
    entries = sorted(p.name for p in (cache / "ycb").iterdir())
    assert all(not e.startswith(".") for e in entries) and len(entries) == len(OBJECTS) + 2
    for e in entries:
        assert {p.name for p in (cache / "ycb" / e).iterdir()} >= {"meta.json", "arrays.npz",
                                                                  "visual.obj", "collision.obj"}


def test_missing_models_name_the_setting(monkeypatch, tmp_path, cache):
    monkeypatch.delenv(YCB_DIR_ENV, raising=False)
    with pytest.raises(FileNotFoundError, match=YCB_DIR_ENV):
        ycb_dir()
    with pytest.raises(FileNotFoundError, match=YCB_DIR_ENV) as err:
        load_ycb_object("013_apple", ycb_dir=tmp_path / "nowhere", cache_dir=cache)
    assert str(tmp_path / "nowhere") in str(err.value) and "google_16k/textured.obj" in str(err.value)
    monkeypatch.setenv(YCB_DIR_ENV, str(tmp_path))  # a folder without the object
    assert ycb_dir() == tmp_path
    with pytest.raises(FileNotFoundError, match=YCB_DIR_ENV) as err:
        load_ycb_object("013_apple", cache_dir=cache)
    msg = str(err.value)
    assert str(tmp_path / "013_apple" / "google_16k" / "textured.obj") in msg
    assert all(name in msg for name in YCB_INFO)
    with pytest.raises(KeyError, match="002_master_chef_can"):
        load_ycb_object("999_unicorn", ycb_dir=tmp_path, cache_dir=cache)


def _drop_scene(asset, drop: float = 0.05):
    mjcf = _mjcf()
    scene = mjcf.RootElement(model="scene")
    scene.option.timestep = 0.002
    scene.worldbody.add("geom", name="floor", type="plane", size=[1, 1, 0.1])
    frame = scene.attach(ycb_mjcf(asset, "obj"))
    frame.pos = [0, 0, asset.rest_height + drop]
    frame.add("freejoint")
    model = mujoco.MjModel.from_xml_string(scene.to_xml_string(), assets=scene.get_assets())
    return model, mujoco.MjData(model)


@pytest.mark.parametrize("name", ["004_sugar_box", "007_tuna_fish_can", "013_apple"])
def test_mjcf_drop_on_plane(built, name):
    a = built[name]
    model, data = _drop_scene(a)
    body = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, "obj/obj")
    assert model.nbody == 3 and model.njnt == 1  # world, attachment frame (free joint), object
    np.testing.assert_allclose(model.body_mass[body], a.mass)
    np.testing.assert_allclose(model.body_ipos[body], a.com, atol=1e-9)
    np.testing.assert_allclose(np.sort(model.body_inertia[body]), np.linalg.eigvalsh(a.inertia), rtol=1e-6)
    vis = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_GEOM, "obj/visual")
    col = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_GEOM, "obj/collision")
    assert model.geom_contype[vis] == model.geom_conaffinity[vis] == 0
    assert model.geom_group[col] == COLLISION_GROUP and model.geom_rgba[col, 3] == 0
    assert (model.geom_matid[vis] >= 0) == (a.texture_path is not None)
    for _ in range(500):  # 1 s
        mujoco.mj_step(model, data)
    rot = data.xmat[body].reshape(3, 3)
    lowest = (data.xpos[body] + a.collision_vertices @ rot.T)[:, 2].min()
    assert -2e-3 < lowest < 2e-3  # resting on the plane: not sunk through, not floating
    assert np.linalg.norm(data.xpos[body, :2]) < 0.2  # no explosion
    if name != "013_apple":  # flat-bottomed: settled upright at its resting height
        assert rot[2, 2] > 0.99 and abs(data.xpos[body, 2] - a.rest_height) < 3e-3
        assert np.abs(data.qvel).max() < 0.05


@pytest.mark.skipif(os.environ.get("BULBJAX_RENDER_TESTS") != "1",
                    reason="compiles Warp render kernels (slow on CPU); BULBJAX_RENDER_TESTS=1")
def test_warp_renders_mesh_texture(built):
    import jax
    import jax.numpy as jnp
    from mujoco import mjx

    a = built["013_apple"]
    mjcf = _mjcf()
    scene = mjcf.RootElement(model="scene")
    scene.worldbody.add("light", pos=[0, 0, 1], dir=[0, 0, -1], directional=True)
    scene.worldbody.add("camera", name="cam", pos=[0, -0.15, 0.2], xyaxes=[1, 0, 0, 0, 0.8, 0.6])
    scene.worldbody.add("geom", type="plane", size=[1, 1, 0.1], rgba=[0.2, 0.2, 0.2, 1])
    frame = scene.attach(ycb_mjcf(a, "obj"))
    frame.pos = [-a.bbox_center[0], -a.bbox_center[1], a.rest_height]
    model = mujoco.MjModel.from_xml_string(scene.to_xml_string(), assets=scene.get_assets())
    mx = mjx.put_model(model, impl="warp")
    d0 = mjx.make_data(model, impl="warp")
    batch = jax.vmap(lambda q: d0.replace(qpos=q))(jnp.asarray(model.qpos0)[None])
    batch = jax.vmap(mjx.forward, in_axes=(None, 0))(mx, batch)
    ctx = mjx.create_render_context(model, nworld=1, cam_res=(64, 64), render_rgb=True,
                                    render_depth=False, use_textures=True, use_shadows=False)
    pt = ctx.pytree()
    rgb, _, _ = mjx.render(mx, mjx.refit_bvh(mx, batch, pt), pt)
    img = np.asarray(mjx.get_rgb(pt, 0, rgb))[0]
    # everything else in the scene is grey (grey floor, white light, white material), so any
    # colour comes from the texture map: a red apple, not flat
    chroma = img.max(-1) - img.min(-1)
    coloured = img[chroma > 0.1]
    assert len(coloured) > 0.05 * 64 * 64
    assert coloured[:, 0].mean() > 2 * coloured[:, 1].mean()
    assert np.std(coloured[:, 0] - coloured[:, 1]) > 0.02
    del ctx


def test_cli_run_without_the_models_is_one_line(monkeypatch, tmp_path, capfd):
    """`bulbjax run` of a YCB domain with $BULBJAX_YCB_DIR pointing nowhere: the CLI's one-line
    error (what to set), no traceback."""
    from bulbjax import cli

    monkeypatch.setenv(YCB_DIR_ENV, str(tmp_path / "nowhere"))
    rc = cli.main(["run", "--env", "ReacherRearrangeYcb", "--small", "--seeds", "1", "--epochs", "1",
                   "--out", str(tmp_path / "run")])
    err = [x for x in capfd.readouterr().err.splitlines() if x.strip()]
    assert rc == 2 and len(err) == 1, err
    assert err[0].startswith("bulbjax: error: YCB models not found: ") and YCB_DIR_ENV in err[0]
