"""GaussianMap: construction, validation, subsets, activations and tensor conversion."""

import numpy as np
import pytest

from gscompress.errors import MapError
from gscompress.gaussians import SH_C0, GaussianMap, random_map


def test_new_fills_defaults_and_casts():
    g = GaussianMap.new(
        np.zeros((4, 3)), np.zeros((4, 1)), np.ones((4, 4)), np.zeros(4), np.zeros((4, 3))
    )
    assert g.means.dtype == np.float32 and g.ids.dtype == np.uint32
    assert g.ids.tolist() == [0, 1, 2, 3]
    assert g.sh_degree == 0 and g.isotropic and not g.has_importance
    assert g.validate() is g


@pytest.mark.parametrize(
    "field, value, message",
    [
        ("means", np.zeros((5, 2)), "means has shape"),
        ("log_scales", np.zeros((5, 2)), "log_scales has shape"),
        ("sh_rest", np.zeros((5, 4, 3)), "coefficients per channel"),
        ("ids", np.zeros(4), "ids has shape"),
    ],
)
def test_bad_shapes_are_refused(field, value, message):
    g = random_map(5)
    kwargs = {name: getattr(g, name) for name in g.__dataclass_fields__}
    kwargs[field] = value
    with pytest.raises(MapError, match=message):
        GaussianMap(**kwargs)


def test_validate_finds_non_finite_duplicate_ids_and_negative_sums():
    g = random_map(10)
    g.means[3, 1] = np.nan
    with pytest.raises(MapError, match=r"means \(x y z\) has 1 non-finite"):
        g.validate()
    g = random_map(10)
    g.ids[2] = g.ids[7]
    with pytest.raises(MapError, match="ids are not unique"):
        g.validate()
    g.ids[:] = [0, 1, 2, 3, 3, 5, 6, 7, 8, 9]  # (ascending but for a repeat)
    with pytest.raises(MapError, match="ids are not unique"):
        g.validate()
    g = random_map(10)
    g.importance_weight[0] = -1
    with pytest.raises(MapError, match="importance_weight has negative"):
        g.validate()
    g = random_map(10)
    g.quats[4] = 0
    with pytest.raises(MapError, match=r"quats \(rot_0..3\) has all-zero rotations"):
        g.validate()


def test_validate_refuses_values_whose_activations_overflow():
    """Finite raw values can still render or rank as inf: a scale of e^1e30, a rotation
    whose squared length overflows float32, a score S / (W + eps) beyond float32."""
    g = random_map(10)
    g.log_scales[1] = 41.0
    with pytest.raises(MapError, match=r"log_scales \(scale_\*\) has values beyond"):
        g.validate()
    g.log_scales[1] = -40.0  # the bound itself is accepted
    g.validate()
    g = random_map(10)
    g.quats[2] = 3e38
    with pytest.raises(MapError, match="too long to normalise"):
        g.validate()
    g = random_map(10)
    g.importance_sum[5], g.importance_weight[5] = 1e31, 0.0
    with pytest.raises(MapError, match="PWAS score"):
        g.validate()


def test_select_by_index_mask_and_slice_agree():
    g = random_map(50, sh_degree=2, isotropic=False)
    idx = np.array([1, 5, 7])
    mask = np.zeros(50, bool)
    mask[idx] = True
    a, b, c = g.select(idx), g.select(mask), g.select(slice(1, 8))
    assert a.equals(b)
    assert len(c) == 7 and c.ids[0] == g.ids[1]
    assert a.sh_rest.shape == (3, 8, 3)
    with pytest.raises(MapError, match="mask has shape"):
        g.select(np.ones(49, bool))


def test_concat_keeps_everything_and_promotes_isotropic():
    a = random_map(20, seed=1, isotropic=True)
    b = random_map(30, seed=2, isotropic=False)
    b.ids += 10_000
    c = GaussianMap.concat([a, b])
    assert len(c) == 50 and not c.isotropic
    np.testing.assert_array_equal(c.log_scales[:20], np.repeat(a.log_scales, 3, axis=1))
    np.testing.assert_array_equal(
        c.importance_sum, np.concatenate([a.importance_sum, b.importance_sum])
    )
    assert c.select(slice(20, 50)).equals(b)


def test_concat_refuses_duplicate_ids_and_mixed_sh():
    a = random_map(10, seed=1)
    with pytest.raises(MapError, match="share Gaussian ids"):
        GaussianMap.concat([a, a])
    b = random_map(10, seed=2, sh_degree=1)
    b.ids += 100
    with pytest.raises(MapError, match="SH degrees"):
        GaussianMap.concat([a, b])


def test_activations():
    g = random_map(100, isotropic=True)
    np.testing.assert_allclose(g.scales(), np.exp(np.repeat(g.log_scales, 3, axis=1)), rtol=1e-6)
    np.testing.assert_allclose(g.opacities(), 1 / (1 + np.exp(-g.opacity_logits)), rtol=1e-6)
    np.testing.assert_allclose(np.linalg.norm(g.rotations(), axis=1), 1.0, rtol=1e-6)
    rgb = g.colors()
    assert rgb.min() >= 0 and rgb.max() <= 1
    inside = np.all(np.abs(g.sh_dc) < 0.5 / SH_C0, axis=1)
    np.testing.assert_allclose(rgb[inside], 0.5 + SH_C0 * g.sh_dc[inside], rtol=1e-6)


def test_importance_score_is_sum_over_weight():
    g = random_map(100)
    np.testing.assert_allclose(g.importance, g.importance_sum / g.importance_weight, rtol=1e-6)
    g.importance_weight[:10] = 0
    g.importance_sum[:10] = 0
    assert g.has_importance and np.all(g.importance[:10] == 0)


def test_tensor_round_trip_is_exact():
    pytest.importorskip("torch")
    g = random_map(64, sh_degree=3, isotropic=False)
    assert GaussianMap.from_tensors(g.to_tensors()).equals(g)


def test_empty_map():
    g = GaussianMap.empty(isotropic=False, sh_degree=1)
    assert len(g) == 0 and not g.isotropic and g.sh_degree == 1
    g.validate()
