"""The smoother's second pass: taken unless it reset to the fixes more often than the first."""
import dataclasses

import torch

from flowins.evaluation.run_report import run_summary
from flowins.navigation import navigate


def test_a_second_pass_that_resets_more_often_than_the_first_is_not_smoothed(monkeypatch, wrong_heading_walk):
    """``smoother_tracks``: the smoother takes the second pass unless that pass reset to the
    fixes more often than the first (each reset counted from the tracks' logs); the run's
    summary says which pass it took."""
    import flowins.navigation as nav
    import flowins.second_pass as sp

    rec, run, config = wrong_heading_walk(2, duration_s=60.0, second_pass=True)
    setup = nav.prepare_navigation(run, config=config)
    inputs = [nav.FilterInput(rec.imu.t_s, rec.imu.acc_mps2, rec.imu.gyro_rps, setup.mean0, setup.cov0, setup.events)]
    (first,) = sp.run_filters(inputs, **config.filter_settings())
    assert sp.heading_fit_record(first) is not None and sp._resets(first) == 0
    real = sp.run_filters
    for extra, chosen in ((0, "second"), (1, "first")):
        def second_pass(rows, **kw):
            return [dataclasses.replace(t, log=t.log + [{"kind": "gnss_reset", "t_s": 1.0}] * extra) for t in real(rows, **kw)]
        monkeypatch.setattr(sp, "run_filters", second_pass)
        (track,), (which,) = sp.smoother_tracks(inputs, [first], config)
        assert which["pass"] == chosen
        assert (track is first) == (chosen == "first")
    monkeypatch.setattr(sp, "run_filters", real)
    result = navigate(run, config=config)
    assert run_summary(result)["smoother_pass"]["pass"] == "second"
    off = navigate(run, config=dataclasses.replace(config, gnss_heading=dataclasses.replace(config.gnss_heading, second_pass=False)))
    assert "smoother_pass" not in run_summary(off)
    torch.testing.assert_close(off.filter.node_mean, result.filter.node_mean, rtol=0, atol=0)
