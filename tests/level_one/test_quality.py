"""The two forms of the proposals' compound-model-aware quality: Progressive-X's code and Eq. 4."""

import numpy as np
import pytest

from evseg_torch.config import LevelOneConfig, config_from_dict, load_config
from evseg_torch.errors import ConfigError
from evseg_torch.level_one.gc_ransac import QUALITIES, _Scoring, gc_ransac, preference
from evseg_torch.level_one.progressive_x import progressive_x
from tests.helpers.level_one import make_scene

# tau = 1 px, so gamma = 1.5 px and gamma^2 = 2.25 px^2: squared errors 0, 0.5625, 1.125, 2.25 and 9
# give preferences 1, 0.75, 0.5, 0 and 0.
THRESHOLD = 1.0
GAMMA2 = 2.25
# Five points: squared errors under the proposal h and under the compound model C (nearest instance).
SQ_H = np.array([0.0, 1.125, 0.5625, 9.0, 0.0])
SQ_C = np.array([9.0, 1.125, 1.125, 0.0, 0.0])


def eq4(sq_h, sq_c):
    """The paper's Eq. 4 as printed: ``|F| - sum_f min(1, max(e_h^2 / gamma^2, 1 - e_C^2 / gamma^2))``."""
    return len(sq_h) - np.sum(np.minimum(1.0, np.maximum(sq_h / GAMMA2, 1.0 - sq_c / GAMMA2)))


def score(quality, sq_h, sq_c, exponent=1.0):
    compound = None if sq_c is None else preference(sq_c, THRESHOLD)
    return float(_Scoring(THRESHOLD, compound, exponent, quality)(preference(sq_h, THRESHOLD)[None])[0])


class TestHandComputed:
    def test_preferences(self):
        np.testing.assert_allclose(preference(SQ_H, THRESHOLD), [1.0, 0.5, 0.75, 0.0, 1.0])
        np.testing.assert_allclose(preference(SQ_C, THRESHOLD), [0.0, 0.5, 0.5, 1.0, 1.0])

    def test_progressive_x_form(self):
        # S = 1 + 0.5 + 0.75 + 0 + 1 = 3.25; shared sum_i min(pref_h, pref_C) = 0 + 0.5 + 0.5 + 0 + 1 = 2.
        assert score("progressive_x", SQ_H, SQ_C) == pytest.approx(3.25 - 2.0)
        assert score("progressive_x", SQ_H, SQ_C, exponent=2.0) == pytest.approx(3.25 - 4.0)

    def test_paper_form(self):
        # Per point min(pref_h, 1 - pref_C): min(1, 1) + min(0.5, 0.5) + min(0.75, 0.5) + 0 + 0 = 2.
        assert score("paper", SQ_H, SQ_C) == pytest.approx(2.0)
        # Eq. 4 as printed: 5 - (0 + 0.5 + 0.5 + 1 + 1) = 2.
        assert eq4(SQ_H, SQ_C) == pytest.approx(2.0)
        # The exponent belongs to Progressive-X's form only.
        assert score("paper", SQ_H, SQ_C, exponent=2.0) == pytest.approx(2.0)

    def test_forms_differ_where_both_fit_part_way(self):
        # Point 3 (pref_h 0.75, pref_C 0.5): Eq. 4 counts 0.5, Progressive-X's form 0.25.
        assert score("paper", SQ_H[2:3], SQ_C[2:3]) == pytest.approx(0.5)
        assert score("progressive_x", SQ_H[2:3], SQ_C[2:3]) == pytest.approx(0.25)
        # pref_h 0.5 below pref_C 0.75: Eq. 4 still counts 0.25 (1 - pref_C), Progressive-X's form 0.
        assert score("paper", np.array([1.125]), np.array([0.5625])) == pytest.approx(0.25)
        assert score("progressive_x", np.array([1.125]), np.array([0.5625])) == pytest.approx(0.0)

    def test_without_compound_both_are_msac(self):
        for quality in QUALITIES:
            assert score(quality, SQ_H, None) == pytest.approx(3.25)
        # Eq. 4 with no instance (e_C infinite) is MSAC too.
        assert eq4(SQ_H, np.full(5, np.inf)) == pytest.approx(3.25)

    def test_paper_form_is_eq4_on_random_errors(self):
        rng = np.random.default_rng(0)
        sq_h, sq_c = rng.uniform(0, 4, (2, 8, 50))
        compound = preference(sq_c, THRESHOLD).max(axis=0)  # nearest of 8 instances
        scores = _Scoring(THRESHOLD, compound, 1.0, "paper")(preference(sq_h, THRESHOLD))
        expected = [eq4(h, sq_c.min(axis=0)) for h in sq_h]
        np.testing.assert_allclose(scores, expected)


class TestProposals:
    def test_default_is_progressive_x(self):
        model, src, dst, dt, _, _ = make_scene(2, "affine4", 3)
        default = progressive_x(src, dst, dt, model, rng=0)
        explicit = progressive_x(src, dst, dt, model, quality="progressive_x", rng=0)
        np.testing.assert_array_equal(default.params, explicit.params)
        np.testing.assert_array_equal(default.labels, explicit.labels)


class TestValidation:
    def test_functions_reject_unknown_quality(self):
        model, src, dst, dt, _, _ = make_scene(0, "translation", 1)
        with pytest.raises(ConfigError, match="quality"):
            gc_ransac(src, dst, dt, model, quality="eq4")
        with pytest.raises(ConfigError, match="quality"):
            progressive_x(src, dst, dt, model, quality="Paper")

    def test_config(self, tmp_path):
        assert LevelOneConfig().quality == "progressive_x"
        assert config_from_dict({"level_one": {"quality": "paper"}}).level_one.quality == "paper"
        with pytest.raises(ConfigError, match=r"level_one\.quality"):
            LevelOneConfig(quality="msac")
        (tmp_path / "c.yaml").write_text("level_one:\n  quality: eq4\n")
        with pytest.raises(ConfigError, match=r"c\.yaml: .*quality"):
            load_config(tmp_path / "c.yaml")
