"""LPIPS from local weights and AVGE."""
from __future__ import annotations


import pytest
import torch



def test_lpips_loads_official_layout_and_is_a_distance(tmp_path):
    from dibrgs_core.common.errors import InputError
    from dibrgs_core.evaluation.lpips import LPIPS, load_lpips
    from dibrgs_core.evaluation.evaluate import avge

    torch.manual_seed(0)
    net = LPIPS("alex")
    with torch.no_grad():
        for k in range(5):
            getattr(net, f"lin{k}").model[1].weight.abs_()
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
