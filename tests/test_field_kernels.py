"""The fused numba CPU kernels (field/cpu_kernels.py via field/cpu_ops.py) against the torch reference samplers:
same values and gradients (features and coordinates), both thread layouts, both gradient-table strategies,
the touched-cell masking of the fused Six-axis level, and exact gradients in float64 (gradcheck)."""

import numpy as np
import pytest
import torch

pytest.importorskip("numba")

from lrslam.field import cpu_kernels  # noqa: E402
from lrslam.field.cpu_ops import cp_product, numba_available, outer_sum, planes_sum, sixaxis_sum, use_numba  # noqa: E402
from lrslam.field.enc_cp import CPLevel  # noqa: E402
from lrslam.field.enc_sixaxis import SixAxisLevel  # noqa: E402
from lrslam.field.enc_triplane import TriPlaneLevel  # noqa: E402
from lrslam.field.interp import resolve_sampler  # noqa: E402
from lrslam.field.model import SceneModel, SceneModelConfig  # noqa: E402

from field_fixtures import assert_same_values_and_gradients, run_and_backprop  # noqa: E402

pytestmark = pytest.mark.skipif(not numba_available(), reason="numba kernels unavailable")

SMALL = (9, 7, 6)          # every cell of every plane touched by the samples
LARGE = (200, 150, 120)    # most cells untouched: exercises the touched-row zeroing / summing


def _levels(shape, sampler):
    torch.manual_seed(0)
    return {"cp": CPLevel(shape, rank=2, channels=32, init_std=0.3, sampler=sampler),
            "sa": SixAxisLevel(shape, rank=16, channels=32, init_std=0.3, sampler=sampler),
            "tri": TriPlaneLevel(shape, channels=32, init_std=0.3, sampler=sampler)}


@pytest.mark.parametrize("threads", [1, 2])
@pytest.mark.parametrize("shape", [SMALL, LARGE], ids=["dense", "sparse"])
def test_numba_levels_match_torch_values_and_gradients(threads, shape):
    old = torch.get_num_threads()
    torch.set_num_threads(threads)
    try:
        x = torch.rand(3000, 3) * 1.2 - 0.1  # some samples outside the bound: border values
        ref, fast = _levels(shape, "gather"), _levels(shape, "numba")
        for name in ref:
            assert_same_values_and_gradients(run_and_backprop(fast[name], fast[name], x),
                                             run_and_backprop(ref[name], ref[name], x))
    finally:
        torch.set_num_threads(old)


def test_reused_gradient_scratch_holds_no_stale_rows():
    # per-thread gradient tables persist between calls and only touched rows are re-zeroed: a second backward
    # over other cells must not see the first call's values
    ref, fast = _levels(LARGE, "gather"), _levels(LARGE, "numba")
    for x in (torch.rand(500, 3) * 0.3, torch.rand(500, 3) * 0.3 + 0.1, torch.rand(500, 3) * 0.3):
        for name in ("sa", "tri"):
            assert_same_values_and_gradients(run_and_backprop(fast[name], fast[name], x),
                                             run_and_backprop(ref[name], ref[name], x))


def test_fused_six_axis_touches_few_cells_and_equals_the_full_planes():
    torch.manual_seed(1)
    lvl = SixAxisLevel(LARGE, rank=4, channels=16, init_std=0.5, sampler="numba")
    x = torch.rand(50, 3) * 0.1 + 0.4  # a small blob: a few cells per plane
    full = sum(planes_sum([P], [(x[:, a], x[:, b])]) for P, (a, b) in zip(lvl.planes(), ((0, 1), (1, 2), (2, 0))))
    pairs = [(lvl.x_y, lvl.y_x), (lvl.y_z, lvl.z_y), (lvl.z_x, lvl.x_z)]
    fused = sixaxis_sum(pairs, [(x[:, 0], x[:, 1]), (x[:, 1], x[:, 2]), (x[:, 2], x[:, 0])])
    torch.testing.assert_close(fused, full, atol=1e-6, rtol=1e-5)
    # mark_cells: exactly the 4 corner rows of each sample's cell
    base = np.array([[0], [7]], np.int64)
    mask = (np.zeros(30, np.bool_),)
    cpu_kernels.mark_cells(base, np.array([5], np.int64), mask)
    assert sorted(np.flatnonzero(mask[0])) == [0, 1, 5, 6, 7, 8, 12, 13]


def test_numba_functions_have_exact_gradients_float64():
    torch.manual_seed(2)
    dt = torch.float64
    x = (torch.rand(40, 3, dtype=dt) * 0.9 + 0.05).requires_grad_()
    lx, ly, lz = (torch.randn(n, 2 * 3, dtype=dt, requires_grad=True) for n in (5, 4, 6))
    assert torch.autograd.gradcheck(lambda *a: cp_product(*a, rank=2), (lx, ly, lz, x))
    P1 = torch.randn(5, 4, 3, dtype=dt, requires_grad=True)
    P2 = torch.randn(6, 5, 3, dtype=dt, requires_grad=True)
    assert torch.autograd.gradcheck(lambda p1, p2, xx: planes_sum([p1, p2], [(xx[:, 0], xx[:, 1]),
                                                                               (xx[:, 2], xx[:, 0])]), (P1, P2, x))
    la, lb = (torch.randn(n, 4, 3, dtype=dt, requires_grad=True) for n in (5, 6))
    assert torch.autograd.gradcheck(outer_sum, (la, lb))
    assert torch.autograd.gradcheck(lambda a, b, xx: sixaxis_sum([(a, b)], [(xx[:, 0], xx[:, 2])]), (la, lb, x))


def test_numba_sampler_selection_and_fallbacks():
    assert resolve_sampler("auto", "cpu") == "numba"
    assert resolve_sampler("gather", "cpu") == "gather"
    assert use_numba("numba", torch.zeros(3)) and not use_numba("gather", torch.zeros(3))
    assert not use_numba("numba", torch.zeros(3, dtype=torch.float16))  # half precision -> torch kernels
    # float64 runs in the kernels too (separately compiled) and matches the torch path
    lvl = TriPlaneLevel(SMALL, channels=8, init_std=0.1, sampler="numba").double()
    ref = TriPlaneLevel(SMALL, channels=8, init_std=0.1, sampler="gather").double()
    ref.load_state_dict(lvl.state_dict())
    x = torch.rand(20, 3, dtype=torch.float64)
    torch.testing.assert_close(lvl(x), ref(x))
    # the default model on CPU uses the kernels for every level
    m = SceneModel(np.array([[-1.0, 1.0], [-1.0, 1.0], [0.0, 1.5]]), SceneModelConfig())
    assert {lv.sampler for lv in m.geometry.levels} == {"numba"}
    assert {lv.sampler for lv in m.appearance.levels} == {"numba"}


def test_frozen_model_uses_cached_planes_with_the_kernels():
    m = SceneModel(np.array([[-1.0, 1.0], [-1.0, 1.0], [0.0, 1.5]]), SceneModelConfig())
    p = (torch.rand(200, 3) * 2 - 1).requires_grad_()
    before = m.colour(p)
    with m.frozen():
        after = m.colour(p)
        after.sum().backward()  # pose gradients still reach the points through the cached planes
        assert m.appearance.levels[1]._cache is not None
    torch.testing.assert_close(after, before.detach(), atol=1e-6, rtol=1e-5)
    assert p.grad is not None and torch.isfinite(p.grad).all() and p.grad.abs().sum() > 0


def test_nan_coordinates_give_nan_features_not_a_crash():
    # a diverged pose puts NaN into the sample positions: indices must stay in range for the unchecked kernels
    x = torch.rand(100, 3)
    x[::7, 1] = float("nan")
    x[3] = float("inf")
    for name, level in _levels(LARGE, "numba").items():
        xi = x.clone().requires_grad_()
        out = level(xi)
        assert torch.isnan(out[::7]).all(), name
        assert torch.isfinite(out[1:7]).all() and torch.isfinite(out[3]).all(), name
        out.sum().backward()  # no crash, gradients exist
        assert xi.grad is not None
