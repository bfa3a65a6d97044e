"""A solve that overflows is refused by name, never published as finite depth (issue 16).

No input found reaches it once ``max_irradiance`` holds, so the overflow is
made inside a real solve: the near-light solver's ln r is pushed past
``ln(float32 max)`` at a few nodes, as an unbounded characteristic would.
"""

from __future__ import annotations

import numpy as np
import pytest

import endo_sfs.relative_depth as relative_depth
from endo_sfs.errors import SolutionRangeError
from endo_sfs.options import SfsOptions
from endo_sfs.relative_depth import solve
from endo_sfs.synthetic import near_light_surface, render_near_light, scene_camera

SIZE = 48


# numpy warns when the float64 depth is cast to float32: the overflow under test
@pytest.mark.filterwarnings("ignore:overflow encountered in cast:RuntimeWarning")
def test_an_overflowing_near_light_solve_is_a_solution_range_error(monkeypatch):
    camera = scene_camera(SIZE)
    image = render_near_light(camera, near_light_surface("sphere")).irradiance
    options = SfsOptions(threads=1)
    good = solve(image, camera, options)
    assert np.isfinite(good.depth).any() and np.nanmin(good.depth) > 0.0

    real = relative_depth.solve_near_light

    def overflowing(*args, **kwargs):
        log_r, slope, info = real(*args, **kwargs)
        log_r = log_r.copy()
        finite = np.flatnonzero(np.isfinite(log_r))
        log_r.flat[finite[len(finite) // 2 : len(finite) // 2 + 3]] = 800.0  # exp → inf
        return log_r, slope, info

    monkeypatch.setattr(relative_depth, "solve_near_light", overflowing)
    with pytest.raises(SolutionRangeError,
                       match=r"near_light solve overflowed: \d+ pixels") as error:
        solve(image, camera, options)
    assert len(str(error.value).splitlines()) == 1
