"""Scene model: ESLAM bound/grid arithmetic, paper parameter counts, encodings' closed forms and equivalences."""

import numpy as np
import pytest
import torch

from lrslam.errors import InputError
from lrslam.field.enc_cp import CPLevel
from lrslam.field.enc_sixaxis import SixAxisLevel
from lrslam.field.enc_triplane import TriPlaneLevel
from lrslam.field.grid import grid_shape, grow_bound
from lrslam.field.interp import sample_lines, sample_plane
from lrslam.field.model import PRESETS, SceneModel, SceneModelConfig

from field_fixtures import assert_same_values_and_gradients, run_and_backprop

REPLICA_ROOM0 = np.array([[-1.9, 7.9], [-2.2, 4.5], [-2.5, 2.3]])


def test_grow_bound_and_grid_shapes_match_eslam_float32():
    b = grow_bound(REPLICA_ROOM0)
    np.testing.assert_allclose(b, [[-1.9, 7.94], [-2.2, 4.52], [-2.5, 2.54]], atol=1e-5)
    # float32 rounding: y side 6.72 / 0.24 = 27.999998 -> 27 (as ESLAM's torch code computes it)
    assert grid_shape(b, 0.24) == (41, 27, 21)
    assert grid_shape(b, 0.06) == (164, 111, 84)
    assert grid_shape(b, 0.03) == (328, 223, 168)


def test_replica_room0_parameter_counts_match_paper():
    lr = SceneModel(REPLICA_ROOM0, SceneModelConfig.preset("lrslam")).parameter_count()
    es = SceneModel(REPLICA_ROOM0, SceneModelConfig.preset("eslam")).parameter_count()
    # closed forms: CP k C (nx+ny+nz), Six-axis 2 k C (nx+ny+nz), tri-plane C (nx ny + nx nz + ny nz), per level
    assert lr["geometry"] == 2 * 32 * (41 + 27 + 21) + 2 * 32 * (164 + 111 + 84)
    assert lr["appearance"] == 2 * 16 * 32 * (41 + 27 + 21) + 2 * 16 * 32 * (328 + 223 + 168)
    tri = lambda n: 32 * (n[0] * n[1] + n[0] * n[2] + n[1] * n[2])  # noqa: E731
    assert es["geometry"] == tri((41, 27, 21)) + tri((164, 111, 84))
    assert es["appearance"] == tri((41, 27, 21)) + tri((328, 223, 168))
    # paper Table 1 (millions): LRSLAM 0.03 / 0.83 / 0.86, ESLAM 1.40 / 5.38 / 6.79
    for counts, paper in ((lr, (0.03, 0.83, 0.86)), (es, (1.40, 5.38, 6.79))):
        for key, value in zip(("geometry", "appearance", "total"), paper):
            assert abs(counts[key] / 1e6 - value) <= 0.03 * value + 0.005, (key, counts[key], value)
    for c in (lr, es):  # the paper's Total includes the decoders (ESLAM's 2,693 weights here)
        assert c["encodings"] == c["geometry"] + c["appearance"] and c["total"] == c["encodings"] + c["decoders"]
        assert 2_000 < c["decoders"] < 5_000


def test_parameters_grow_linearly_for_low_rank_and_quadratically_for_triplane():
    base = np.array([[0.0, 2.4], [0.0, 2.4], [0.0, 2.4]]) - 1e-3  # keeps float32 sides off exact multiples
    counts = {}
    for name in ("cp-sa", "triplane"):
        cfg = SceneModelConfig.preset(name)
        counts[name] = [SceneModel(base * s, cfg).parameter_count()["encodings"] for s in (1, 2, 4)]
    lr, tp = np.array(counts["cp-sa"], float), np.array(counts["triplane"], float)
    np.testing.assert_allclose(lr[1:] / lr[0], [2, 4], rtol=0.08)
    np.testing.assert_allclose(tp[1:] / tp[0], [4, 16], rtol=0.15)


def test_presets_and_encoding_outputs():
    bound = np.array([[-1.0, 1.0], [-1.0, 1.0], [0.0, 1.5]])
    p = torch.rand(100, 3) * 2 - 1
    for name in PRESETS:
        m = SceneModel(bound, SceneModelConfig.preset(name))
        sdf, rgb = m.sdf(p), m.colour(p)
        assert sdf.shape == (100,) and rgb.shape == (100, 3)
        assert torch.all(sdf.abs() < 1) and torch.all((rgb > 0) & (rgb < 1))
        assert m.geometry.features(p).shape == (100, 64) and m.appearance.features(p).shape == (100, 64)
    kinds = {n: (SceneModelConfig.preset(n).geometry.kind, SceneModelConfig.preset(n).appearance.kind)
             for n in ("lrslam", "cp-cp", "sa-sa", "sa-cp", "eslam")}
    assert kinds == {"lrslam": ("cp", "sa"), "cp-cp": ("cp", "cp"), "sa-sa": ("sa", "sa"), "sa-cp": ("sa", "cp"),
                     "eslam": ("triplane", "triplane")}
    assert SceneModelConfig() == SceneModelConfig.preset("lrslam")
    with pytest.raises(InputError):
        SceneModelConfig.preset("tensorf")
    with pytest.raises(InputError):
        SceneModel(np.array([[0, 1], [0, 1], [1, 0]]))


def test_cp_level_at_grid_nodes_is_the_closed_form():
    torch.manual_seed(0)
    lvl = CPLevel((5, 4, 3), rank=2, channels=3, init_std=1.0)
    i, j, k = 3, 1, 2
    x01 = torch.tensor([[i / 4, j / 3, k / 2]])
    expected = (lvl.x[i] * lvl.y[j] * lvl.z[k]).sum(0)
    torch.testing.assert_close(lvl(x01)[0], expected, rtol=1e-6, atol=1e-6)


def test_linear_and_bilinear_interpolation_closed_forms_and_border():
    line = torch.tensor([[0.0], [10.0], [30.0]])
    out = sample_lines(line, torch.tensor([0.0, 0.25, 0.75, 1.0, -0.5, 2.0]))
    torch.testing.assert_close(out[:, 0], torch.tensor([0.0, 5.0, 20.0, 30.0, 0.0, 30.0]))
    plane = torch.arange(6.0).view(2, 3, 1)  # value = 3 a + b at node (a, b)
    xa, xb = torch.tensor([0.5, 1.0]), torch.tensor([0.25, 1.0])
    for s in ("gather", "ebag", "grid_sample"):
        torch.testing.assert_close(sample_plane(plane, xa, xb, s)[:, 0], torch.tensor([1.5 + 0.5, 5.0]))


@pytest.mark.parametrize("sampler", ["gather", "grid_sample", "numba"])
def test_six_axis_materialised_equals_direct_values_and_gradients(sampler):
    torch.manual_seed(1)
    mat = SixAxisLevel((23, 17, 11), rank=16, channels=8, init_std=0.3, sampler=sampler)
    direct = SixAxisLevel((23, 17, 11), rank=16, channels=8, init_std=0.3, sampler=sampler, evaluation="direct")
    direct.load_state_dict(mat.state_dict())
    x = torch.rand(500, 3, dtype=torch.float32)
    assert_same_values_and_gradients(run_and_backprop(mat, mat, x), run_and_backprop(direct, direct, x))


def test_plane_samplers_agree_on_values_and_gradients():
    torch.manual_seed(2)
    lvl = TriPlaneLevel((9, 8, 7), channels=4, init_std=1.0, sampler="gather")
    x = torch.rand(300, 3)
    ref = None
    for s in ("gather", "ebag", "grid_sample"):
        lvl.sampler = s
        xi = x.clone().requires_grad_()
        out = lvl(xi)
        out.square().sum().backward()
        got = (out.detach(), xi.grad, *(p.grad.clone() for p in lvl.parameters()))
        lvl.zero_grad()
        if ref is None:
            ref = got
        for a, b in zip(ref, got):
            torch.testing.assert_close(a, b, atol=2e-4, rtol=1e-4)


def test_frozen_context_caches_planes_and_restores_gradients():
    m = SceneModel(np.array([[-1.0, 1.0], [-1.0, 1.0], [0.0, 1.5]]))
    p = torch.rand(50, 3)
    before = m.colour(p).detach()
    with m.frozen():
        assert not any(q.requires_grad for q in m.parameters())
        torch.testing.assert_close(m.colour(p), before)
        torch.testing.assert_close(m.colour(p), before)  # second call served from the cache
        assert m.appearance.levels[1]._cache is not None
    assert all(q.requires_grad for q in m.parameters())
    assert m.appearance.levels[1]._cache is None


@pytest.mark.parametrize("rank", [2, 16])
def test_chunked_cp_evaluation_matches_plain_autograd(rank):
    torch.manual_seed(3)
    lvl = CPLevel((13, 9, 7), rank=rank, channels=32, init_std=0.5)
    x = torch.rand(9000, 3)  # more samples than one CPU chunk (4096 samples for k C = 64, 512 for 512)

    def reference(xi):  # plain autograd: interpolate each line, multiply, sum over the rank
        f = [sample_lines(L.view(L.shape[0], -1), xi[:, a]) for a, L in enumerate((lvl.x, lvl.y, lvl.z))]
        return (f[0] * f[1] * f[2]).view(-1, rank, 32).sum(1)

    assert_same_values_and_gradients(run_and_backprop(lvl, lvl, x), run_and_backprop(reference, lvl, x))
