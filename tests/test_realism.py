"""The GelSight renderer against a real sensor's ball presses (skips without ../shared/real)."""

from __future__ import annotations

import pytest

from vs2t_edge.sim.realism import DEFAULT_CALIB, fit_and_report

pytestmark = pytest.mark.skipif(not (DEFAULT_CALIB / "dataPack_small.npz").is_file(),
                                reason="../shared/real/taxim_calib absent (fresh machine)")


def test_fitted_lights_cut_the_colour_error_on_held_out_real_presses():
    res = fit_and_report(DEFAULT_CALIB)
    before, after, shipped = res["before"], res["after"], res["shipped"]
    # rendering the press must beat rendering nothing, and the fit must beat the guess clearly
    assert after["contact_mae"] < 0.6 * after["contact_mae_if_no_press_rendered"]
    assert after["contact_mae"] < 0.6 * before["contact_mae"]
    # the coefficients in sim/gelsight.py are the ones this fit produces
    assert abs(shipped["contact_mae"] - after["contact_mae"]) < 0.5
