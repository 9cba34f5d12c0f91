"""Training runs: resume to identical parameters, extreme settings, and the CLI end to end on the tiny scene."""
from __future__ import annotations

import json
import re
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from dibrgs_core.training.config import preset
from dibrgs_core.training.checkpoint import MODEL
from dibrgs_core.training.methods import TrainingFailed
from dibrgs_core.training.trainer import Trainer, train

from train_synth import make_synth_scene

torch.set_num_threads(1)


@pytest.fixture(scope="module")
def synth_init(synth, tmp_path_factory) -> Path:
    """A finished short run on the synthetic scene; later runs reuse its init/ and pseudo/ caches."""
    work = tmp_path_factory.mktemp("runs") / "base"
    cfg = _cfg(40)
    train(synth, work, cfg)
    return work


def _cfg(iterations: int, method: str = "dibrgs"):
    cfg = preset("test")
    cfg.iterations = iterations
    cfg.method = method
    cfg.curve_every_s = 1e9  # curve points at start and end only
    cfg.curve_max_views = 2
    cfg.model.max_init_anchors = 300
    return cfg


def _with_caches(base: Path, work: Path) -> Path:
    work.mkdir(parents=True)
    for sub in ("init", "pseudo"):
        if (base / sub).exists():
            shutil.copytree(base / sub, work / sub)
    return work


def _params(work: Path) -> dict[str, torch.Tensor]:
    st = torch.load(work / MODEL, map_location="cpu", weights_only=False)
    out = dict(st["model"])
    if st.get("ibr_feats") is not None:
        out["ibr_feats"] = st["ibr_feats"]
    return out


def _assert_finite(work: Path) -> None:
    for k, v in _params(work).items():
        assert torch.isfinite(v).all(), f"{k} has non-finite values"


@pytest.mark.parametrize("colour", ["off", "on"])
def test_resume_continues_to_identical_parameters(synth, synth_init, tmp_path, colour):
    """A run stopped half-way (as by SIGTERM) and resumed ends with exactly the parameters of an
    uninterrupted run: RNG states, optimiser moments, growth statistics and view orders are restored;
    with per-view colour transforms on, the transforms and their optimiser too."""
    def cfg():
        c = _cfg(60)
        c.colour.mode = colour
        return c

    a = _with_caches(synth_init, tmp_path / "a")
    ra = train(synth, a, cfg())
    b = _with_caches(synth_init, tmp_path / "b")
    rb1 = train(synth, b, cfg(), stop_after=27)
    assert rb1.status == "interrupted" and rb1.iteration == 27
    assert (b / "checkpoint.pt").exists() and not (b / MODEL).exists()
    rb2 = train(synth, b, cfg(), resume=True)
    assert rb2.status == "done" and rb2.iteration == ra.iteration == 60
    pa, pb = _params(a), _params(b)
    assert pa.keys() == pb.keys()
    for k in pa:
        assert torch.equal(pa[k], pb[k]), k
    # The curve continues across the interruption.
    rows = (b / "curve.csv").read_text().strip().splitlines()
    assert rows[0] == "seconds,iteration,psnr,ssim" and rows[1].split(",")[1] == "0" and rows[-1].split(",")[1] == "60"
    if colour == "on":
        ta, tb = (json.loads((w / "report.json").read_text())["values"]["colour_transforms"] for w in (a, b))
        assert ta == tb and len(ta) == 3


@pytest.mark.slow
def test_the_no_dense_init_ablation_starts_from_the_sfm_points(tmp_path, capsys):
    """``--no-dense-init`` (the paper's "w/o Dense Init."): anchors from the SfM points alone, fewer
    than the dense cloud gives, and the report says so with the count. Without any SfM point
    (two 64-pixel photos of the scene) it stops at once, saying the ablation has nothing to start
    from, instead of failing inside the model's construction."""
    from geom_synth import make_synthetic_scene

    from dibrgs_core.cli import main
    from dibrgs_core.data.levir import write_scene

    def run(size: int, name: str, *extra: str) -> tuple[int, Path]:
        root = write_scene(tmp_path / f"scene{size}", make_synthetic_scene(size)[0].views)
        work = tmp_path / name
        return main(["train", str(root), "--out", str(work), "--preset", "test", "--iterations", "1",
                     "--train", "all", "--no-pseudo", "--threads", "1", *extra]), work

    rc, sparse = run(96, "sparse", "--no-dense-init")
    assert rc == 0
    steps = {d["step"]: d for d in json.loads((sparse / "report.json").read_text())["decisions"]}
    assert steps["dense_init"]["applied"] is False
    n = int(re.fullmatch(r"ablation --no-dense-init: anchors from (\d+) SfM points", steps["dense_init"]["reason"])[1])
    init = json.loads((sparse / "init" / "init_report.json").read_text())["values"]
    assert 0 < n == init["sfm_points"] < init["points"]
    rc, dense = run(96, "dense")
    assert rc == 0
    assert 0 < _params(sparse)["anchor"].shape[0] <= n < _params(dense)["anchor"].shape[0]
    capsys.readouterr()
    rc, none = run(64, "none", "--no-dense-init", "--train", "000,002")  # two 64-pixel photos: no SfM point
    err = capsys.readouterr().err.strip().splitlines()[-1]
    assert rc == 2 and not (none / MODEL).exists()
    assert err.startswith("dibrgs train: error: --no-dense-init: SfM triangulated no points"), err


def test_progress_json_lines_and_report(synth, synth_init, tmp_path):
    import io

    work = _with_caches(synth_init, tmp_path / "p")
    buf = io.StringIO()
    Trainer(synth, work, _cfg(30), progress_json=True, stream=buf).run()
    lines = [json.loads(x) for x in buf.getvalue().splitlines()]
    prog = [x for x in lines if "iteration" in x and "done" not in x]
    assert prog and all({"iteration", "total", "loss", "eta_s", "elapsed_s"} <= x.keys() for x in prog)
    assert prog[-1]["iteration"] == 30 and prog[-1]["eta_s"] == pytest.approx(0.0, abs=1e-6)
    assert lines[-1]["done"] is True and lines[-1]["work"] == str(work)
    rep = json.loads((work / "report.json").read_text())
    steps = {d["step"]: d for d in rep["decisions"]}
    assert steps["pseudo_views"]["applied"] and steps["ibr_features"]["details"]["encoder"] == "pyramid"
    assert "dense_init" in steps and "height_constraint" in steps
    hf = steps["pseudo_depth_height_field"]
    assert isinstance(hf["applied"], bool) and ("deg from straight down" in hf["reason"] or "up axis" in hf["reason"])
    assert 0.0 <= rep["values"]["pseudo_rejected_fraction"] < 0.9


def test_progress_json_announces_the_long_set_up_stages(synth, tmp_path):
    """A fresh run says what it is doing before the first iteration (geometry, then each pseudo
    view built, counted up to the total): the add-on shows it instead of a frozen bar. A run
    that reuses both caches announces neither."""
    import io

    from dibrgs_core.bridge.progress import Progress

    buf = io.StringIO()
    Trainer(synth, tmp_path / "fresh", _cfg(3), progress_json=True, stream=buf).run()
    lines = [json.loads(x) for x in buf.getvalue().splitlines()]
    first_it = next(i for i, x in enumerate(lines) if "iteration" in x)
    stages = [x for x in lines if "stage" in x]
    assert stages and all(lines.index(x) < first_it for x in stages)
    assert stages[0]["stage"].startswith("geometry initialisation")
    pv = [x for x in stages if x["stage"] == "building pseudo views"]
    total = pv[0]["total"]
    assert total > 0 and [x["done"] for x in pv] == list(range(total + 1))
    state = Progress()
    for x in lines[:first_it]:
        state.update(x)
    assert state.fraction == 1.0 and state.stage == "building pseudo views"

    again = io.StringIO()
    Trainer(synth, _with_caches(tmp_path / "fresh", tmp_path / "again"), _cfg(3), progress_json=True,
            stream=again).run()
    assert not [x for x in map(json.loads, again.getvalue().splitlines()) if "stage" in x]


def test_ablation_flags_switch_components_off(synth, synth_init, tmp_path):
    work = _with_caches(synth_init, tmp_path / "abl")
    cfg = _cfg(12)
    cfg.pseudo.mode = "off"
    cfg.ibr = "none"
    cfg.height = "off"
    train(synth, work, cfg)
    steps = {d["step"]: d["applied"] for d in json.loads((work / "report.json").read_text())["decisions"]}
    assert steps["pseudo_views"] is False and steps["ibr_features"] is False
    assert steps["height_constraint"] is False
    st = torch.load(work / MODEL, weights_only=False)
    assert st["ibr_feats"] is None and not any(k.startswith("e_mod") for k in st["model"])


@pytest.mark.slow
def test_ground_level_views_leave_out_the_height_parts(tmp_path):
    """Photos taken at ground level looking sideways (a facade survey, not an aerial one): the run
    decides from the scene that the height field's parts do not apply (no height map, so no
    height constraint; no up axis for the pseudo views' depth), says why, and trains."""
    from geom_synth import make_synthetic_scene

    from dibrgs_core.data.levir import write_scene

    scene, _ = make_synthetic_scene(32, n_views=6, horizontal=True)  # 6 s: ray-marched to the horizon
    write_scene(tmp_path / "s", scene.views)
    cfg = _cfg(5)
    cfg.depth_prior = "gt"  # the oracle's depth: this checks the decisions, not the plane sweep
    res = Trainer(tmp_path / "s", tmp_path / "w", cfg, train_ids=["000", "002", "004"],
                  test_ids=["001", "003", "005"]).run()
    assert res.status == "done"
    init = {d["step"]: d for d in json.loads((tmp_path / "w" / "init" / "init_report.json").read_text())["decisions"]}
    assert not init["height_map"]["applied"] and not init["overlap_removal"]["applied"]
    steps = {d["step"]: d for d in json.loads((tmp_path / "w" / "report.json").read_text())["decisions"]}
    assert not steps["height_constraint"]["applied"]
    assert "built no height map" in steps["height_constraint"]["reason"]
    hf = steps["pseudo_depth_height_field"]
    assert not hf["applied"] and "up axis is ambiguous" in hf["reason"]
    assert steps["pseudo_views"]["applied"]
    st = torch.load(tmp_path / "w" / MODEL, weights_only=False)
    assert all(torch.isfinite(v).all() for v in st["model"].values() if torch.is_tensor(v) and v.is_floating_point())


# -- extremes -------------------------------------------------------------------------
@pytest.mark.stability
@pytest.mark.parametrize("factor", [1e4, 1e-8])
def test_extreme_learning_rates_stay_finite(synth, synth_init, tmp_path, factor):
    """Every learning rate multiplied by 1e4 or 1e-8: the run ends with finite parameters and IBR
    features (non-finite steps are skipped), or stops with a clear message."""
    work = _with_caches(synth_init, tmp_path / f"lr{factor:g}")
    cfg = _cfg(30)
    lr = cfg.lr
    for name in ("offset", "mlp_opacity", "mlp_cov", "mlp_color", "ibr_fusion"):
        a, b = getattr(lr, name)
        setattr(lr, name, (a * factor, b * factor))
    lr.anchor_feat *= factor
    lr.scaling *= factor
    lr.projection *= factor
    try:
        res = train(synth, work, cfg)
    except TrainingFailed as e:
        assert "anchor" in str(e)
        return
    assert res.status == "done"
    _assert_finite(work)
    curve = (work / "curve.csv").read_text().strip().splitlines()[1:]
    assert all(np.isfinite(float(r.split(",")[2])) for r in curve)


@pytest.mark.stability
def test_all_black_images_train_to_a_finite_model(tmp_path):
    """A scene whose images are all black (no SfM points, no texture): the geometry falls back, training
    ends with finite parameters and renders black."""
    from dibrgs_core.data.scene import View
    from dibrgs_core.data.levir import read_scene, write_scene

    src = make_synth_scene(tmp_path / "src", resolution=24)
    sc = read_scene(src)
    views = {k: View(v.camera, np.zeros_like(v.image), v.depth) for k, v in sc.views.items()}
    black = write_scene(tmp_path / "black", views, sc.track)
    work = tmp_path / "w"
    res = train(black, work, _cfg(20))
    assert res.status == "done"
    _assert_finite(work)
    from dibrgs_core.evaluation.evaluate import load_trained

    img, depth = load_trained(work).render(sc.test_views()[0].camera)
    assert np.isfinite(img).all() and np.isfinite(depth).all() and img.mean() < 0.2


@pytest.mark.stability
def test_pseudo_view_without_valid_pixels_is_left_out(synth, synth_init, tmp_path):
    """A pseudo-view camera that looks away from the scene gets no warped pixel: it is left out with a
    reason in the report, and training still ends finite."""
    from dibrgs_core.camera.serialize import camera_to_dict
    from dibrgs_core.camera.pinhole import look_at
    from dibrgs_core.data.levir import read_scene

    cam = read_scene(synth).train_views()[0].camera
    away = type(cam)(K=cam.K, w2c=look_at(cam.center, cam.center + (cam.center - np.zeros(3)), [0, 0, 1.0]),
                     width=cam.width, height=cam.height, name="away")
    path = tmp_path / "path.json"
    path.write_text(json.dumps([camera_to_dict(away)]))
    work = _with_caches(synth_init, tmp_path / "pv")
    cfg = _cfg(20)
    cfg.pseudo_path = str(path)
    train(synth, work, cfg)
    d = {x["step"]: x for x in json.loads((work / "report.json").read_text())["decisions"]}
    assert d["pseudo_views"]["applied"] is False and "without any filled pixel" in d["pseudo_views"]["reason"]
    _assert_finite(work)


def test_padded_pseudo_pixels_get_their_loss_weight(synth, synth_init, tmp_path):
    """Pseudo-view pixels filled by padding are weighted by ``pseudo.padded_weight`` in the loss
    mask, warped pixels by 1, holes by 0 (0 masks padding out entirely)."""
    masks = {}
    for w in (1.0, 0.25, 0.0):
        cfg = _cfg(20)
        cfg.pseudo.padded_weight = w
        tr = Trainer(synth, _with_caches(synth_init, tmp_path / f"w{w}"), cfg)
        tr.setup()
        masks[w] = torch.stack([f.mask for f in tr.pseudo_frames])
    padded = (masks[1.0] == 1) & (masks[0.0] == 0)
    assert padded.any() and (masks[0.0] == 1).any()
    assert torch.equal(masks[0.25][padded], torch.full((int(padded.sum()),), 0.25))
    assert torch.equal(masks[0.25][~padded], masks[1.0][~padded])
    assert set(masks[0.25].unique().tolist()) <= {0.0, 0.25, 1.0}


@pytest.mark.stability
def test_all_anchors_pruned_stops_with_a_clear_message(synth, synth_init, tmp_path):
    """An impossible opacity floor prunes every anchor: training stops with a message saying so
    instead of writing a model without Gaussians."""
    work = _with_caches(synth_init, tmp_path / "prune")
    cfg = _cfg(100)
    cfg.growth.min_opacity = 1e9
    with pytest.raises(TrainingFailed, match="every anchor was pruned"):
        train(synth, work, cfg)
    assert not (work / MODEL).exists()


# -- CLI end to end on the Blender-rendered tiny scene -------------------------------
def _dibrgs(*args: str, timeout: int = 600) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "dibrgs_core", *args], capture_output=True, text=True,
                          timeout=timeout)


@pytest.mark.slow
def test_cli_train_eval_render_export_on_tiny_scene(tiny_scene, tmp_path):
    """`dibrgs train --preset test` on the 64x64 city raises the held-out PSNR above the initial render's;
    eval writes metrics (LPIPS unavailable without weights), render and export write readable files."""
    import trimesh

    work = tmp_path / "work"
    r = _dibrgs("train", str(tiny_scene), "--out", str(work), "--preset", "test", "--progress-json")
    assert r.returncode == 0, r.stderr[-3000:]
    last = json.loads(r.stdout.strip().splitlines()[-1])
    assert last["done"] is True
    rows = [x.split(",") for x in (work / "curve.csv").read_text().strip().splitlines()[1:]]
    first, final = float(rows[0][2]), float(rows[-1][2])
    assert final > first + 1.0, (first, final)
    assert (work / "curve.png").stat().st_size > 0
    r = _dibrgs("eval", str(work))
    assert r.returncode == 0, r.stderr[-3000:]
    m = json.loads((work / "metrics.json").read_text())
    assert m["lpips"] is None and m["avge"] is None and "lpips_unavailable" in m
    assert m["views"] == 17 and m["psnr"] > first and m["fps"] > 0
    assert len(list((work / "renders").glob("*.png"))) == 17
    out = tmp_path / "track"
    r = _dibrgs("render", str(work), "--cameras", str(tiny_scene / "Cams" / "002.txt"), "--out", str(out))
    assert r.returncode == 0, r.stderr[-3000:]
    assert (out / "002.png").exists() and (out / "002_depth.exr").exists()
    ply = tmp_path / "g.ply"
    r = _dibrgs("export", str(work), "--ply", str(ply))
    assert r.returncode == 0, r.stderr[-3000:]
    v = trimesh.load(ply).metadata["_ply_raw"]["vertex"]["data"]
    assert len(v) > 0 and {"f_dc_0", "opacity", "scale_2", "rot_3"} <= set(v.dtype.names)
    # Bad input: a missing run folder is a clear error, exit code 2.
    r = _dibrgs("eval", str(tmp_path / "nope"))
    assert r.returncode == 2 and "no trained model" in r.stderr
    # The held-out error split by training-view visibility, on the same run.
    script = Path(__file__).resolve().parents[2] / "scripts" / "error_by_visibility.py"
    r = subprocess.run([sys.executable, str(script), str(tiny_scene), str(work), "--json", str(tmp_path / "v.json"),
                        "--png", str(tmp_path / "v.png")], capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr[-3000:]
    split = json.loads((tmp_path / "v.json").read_text())
    assert sum(split["fractions"][k] for k in ("unseen", "one", "two_plus")) == pytest.approx(1.0)
    p = split["runs"][0]["psnr"]
    # Pooled over pixels, "all" is close to (not equal to) the mean of per-view PSNRs.
    assert abs(p["all"] - m["psnr"]) < 1.5, (p, m["psnr"])
    # Pixels more training views see are reconstructed better.
    assert p["two_plus"] > p["unseen"], p
    # "whole image" is dibrgs eval's mean of per-view PSNRs; "seen" pools the two seen groups.
    assert split["runs"][0]["whole_image"] == pytest.approx(m["psnr"], abs=0.05)
    assert min(p["one"], p["two_plus"]) <= split["runs"][0]["seen"] <= max(p["one"], p["two_plus"])
    assert (tmp_path / "v.png").stat().st_size > 0 and "seen by none" in r.stdout
    no_depth = tmp_path / "nodepth"
    shutil.copytree(tiny_scene, no_depth, ignore=shutil.ignore_patterns("Depths"))
    r = subprocess.run([sys.executable, str(script), str(no_depth), str(work)], capture_output=True, text=True,
                       timeout=300)
    assert r.returncode == 2 and "no depth" in r.stderr, r.stderr[-2000:]


def test_pseudo_view_flags_reach_the_config():
    from dibrgs_core.cli import build_parser
    from dibrgs_core.commands.train import config_from_args
    p = build_parser()
    cfg = config_from_args(p.parse_args(["train", "S", "--out", "W", "--preset", "cpu"]))
    assert cfg.pseudo.surface == "auto" and cfg.pseudo.consistency_tol == pytest.approx(0.1)
    cfg = config_from_args(p.parse_args(["train", "S", "--out", "W", "--pseudo-surface", "off",
                                         "--pseudo-consistency", "0"]))
    assert cfg.pseudo.surface == "off" and cfg.pseudo.consistency_tol == 0.0
    # Refused when the command line is parsed (one line naming the option, exit 2).
    for bad in ("-1", "nan"):
        with pytest.raises(SystemExit) as e:
            p.parse_args(["train", "S", "--out", "W", "--pseudo-consistency", bad])
        assert e.value.code == 2


@pytest.mark.parametrize("change,says", [
    (lambda c: setattr(c, "method", "nerf"), "unknown method 'nerf' (dibrgs or 3dgs)"),
    (lambda c: setattr(c, "iterations", 0), "--iterations must be a positive integer, got 0"),
    (lambda c: setattr(c, "iterations", 2.5), "--iterations must be a positive integer, got 2.5"),
    (lambda c: setattr(c, "resolution_scale", 0.0), "--resolution-scale must be in (0, 4], got 0.0"),
], ids=["method", "iterations-0", "iterations-float", "scale-0"])
def test_the_library_checks_a_configuration_before_it_touches_anything(tmp_path, change, says):
    """Called as a library (a user's script), not through the command's options: the same one-line
    errors, before the scene is read or the run folder made."""
    from dibrgs_core.common.errors import InputError

    cfg = _cfg(1)
    change(cfg)
    with pytest.raises(InputError, match=re.escape(says)):
        train(tmp_path / "no scene here", tmp_path / "w", cfg)
    assert not (tmp_path / "w").exists()


def test_the_library_refuses_a_file_as_the_run_folder(tmp_path):
    from dibrgs_core.common.errors import InputError

    (tmp_path / "f").write_text("a file")
    with pytest.raises(InputError, match="is a file, not a folder"):
        train(tmp_path / "no scene here", tmp_path / "f", _cfg(1))
    assert (tmp_path / "f").read_text() == "a file"
