"""LPIPS from local weights and AVGE."""
from __future__ import annotations


import pytest
import torch


def _random_lpips(net: str):
    """LPIPS of the ``net`` backbone with random weights (seeded), its heads made non-negative as
    trained ones are."""
    from dibrgs_core.evaluation.lpips import LPIPS

    torch.manual_seed(0)
    lp = LPIPS(net)
    with torch.no_grad():
        for k in range(5):
            getattr(lp, f"lin{k}").model[1].weight.abs_()
    return lp


def test_lpips_loads_official_layout_and_is_a_distance(tmp_path):
    from dibrgs_core.common.errors import InputError
    from dibrgs_core.evaluation.lpips import load_lpips
    from dibrgs_core.evaluation.evaluate import avge

    net = _random_lpips("alex")
    full = tmp_path / "lpips_alex_full.pth"
    torch.save(net.state_dict(), full)
    assert "net.slice1.0.weight" in net.state_dict() and "lin4.model.1.weight" in net.state_dict()
    lp = load_lpips(full)
    a = torch.rand(40, 40, 3)
    b = (a + 0.2 * torch.randn_like(a)).clamp(0, 1)
    assert float(lp(a, a)) == pytest.approx(0.0, abs=1e-7)
    assert float(lp(a, b)) > 0
    heads = tmp_path / "alex.pth"
    torch.save({k: v for k, v in net.state_dict().items() if k.startswith("lin")}, heads)
    with pytest.raises(InputError, match="backbone"):
        load_lpips(heads)
    bb = tmp_path / "alexnet_tv.pth"
    torch.save({f"features.{k.split('.')[2]}.{k.split('.')[3]}": v for k, v in net.state_dict().items()
                if k.startswith("net.")}, bb)
    lp2 = load_lpips(heads, bb)
    assert float(lp2(a, b)) == pytest.approx(float(lp(a, b)), rel=1e-6)
    with pytest.raises(InputError):
        load_lpips(tmp_path / "missing.pth")
    # AVGE is the geometric mean of MSE, sqrt(1-SSIM) and LPIPS.
    assert avge(20.0, 0.75, 0.1) == pytest.approx((0.01 * 0.5 * 0.1) ** (1 / 3))


@pytest.mark.slow
def test_eval_scores_lpips_and_avge_with_local_weights(finished_run, tmp_path):
    """``dibrgs eval --lpips FILE`` (weights of the lpips package's layout, here random ones saved
    to a file): every held-out view gets an LPIPS, the run's is their mean and AVGE combines it with
    PSNR and SSIM. With AlexNet's weights the run's 24-pixel images are too small for its features
    (31 at least): LPIPS and AVGE are left out, and the metrics and the log say why, instead of an
    internal error from inside the network."""
    import json

    from run_synth import copy_run, dibrgs

    from dibrgs_core.evaluation.evaluate import avge

    def evaluate(net: str) -> dict:
        torch.save(_random_lpips(net).state_dict(), tmp_path / f"lpips_{net}.pth")
        work = copy_run(finished_run, tmp_path / net)
        rc, err = dibrgs("eval", work, "--lpips", tmp_path / f"lpips_{net}.pth", "--threads", "1", "--fps-repeats", "1")
        assert rc == 0, err
        return json.loads((work / "metrics.json").read_text())

    m = evaluate("vgg")
    per_view = [r["lpips"] for r in m["per_view"].values()]
    assert len(per_view) == m["views"] > 0 and all(0 < v < float("inf") for v in per_view)
    assert m["lpips"] == pytest.approx(sum(per_view) / len(per_view))
    assert m["avge"] == pytest.approx(avge(m["psnr"], m["ssim"], m["lpips"])) and 0 < m["avge"] < 1
    assert "lpips_unavailable" not in m
    scored = m
    m = evaluate("alex")
    assert m["lpips"] is None and m["avge"] is None and m["psnr"] == pytest.approx(scored["psnr"])
    assert m["lpips_unavailable"].startswith("the held-out images' shortest side is 24 px, under the 31 px LPIPS-alex")
