"""What the evaluate job says of a run's fitted vehicle mounting."""
from __future__ import annotations

import math

from flowins.evaluation.run_report import mounting_line


def test_the_mounting_line_gives_the_fit_in_degrees_and_says_whether_it_is_used():
    record = {"used": True, "reason": "the fit takes the residual from 0.52 to 0.05 m/s",
              "mount_pitch_rad": math.radians(2.04), "mount_yaw_rad": math.radians(-3.0), "lever_m": [-0.84, 0.0, 0.13],
              "residual_mps": [0.52, 0.05], "samples": 3000}
    line = mounting_line(record)
    assert line.startswith("vehicle mounting fitted: pitch 2.04°, yaw -3.00°, lever arm (-0.84, 0.00, 0.13) m; the fit")
    assert "fitted, not used" in mounting_line(record | {"used": False})
    assert mounting_line({"used": False, "reason": "fit_mounting: 0 samples"}) == \
        "vehicle mounting not fitted: fit_mounting: 0 samples"
