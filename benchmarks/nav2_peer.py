"""nav2's particle filter (PyPI `amcl` 0.1.2, GPL-3, benchmarks extra) set up like ours, for the benchmarks.

Same motion noise (both take Thrun's alphas in std form; nav2's alpha5 is for omni drives only), same
beam-model parameters, our KLD and recovery bounds, the map with its frame, and the laser at the base.
"""

from __future__ import annotations

import numpy as np


def make_nav2(occ, fcfg, *, min_particles: int, max_particles: int, max_beams: int, recovery: bool):
    """An `amcl.AMCL` on `occ` with the filter config's parameters; recovery=False turns augmented MCL off."""
    import amcl

    s, m = fcfg.sensor, fcfg.motion
    slow, fast = (fcfg.alpha_slow, fcfg.alpha_fast) if recovery else (0.0, 0.0)
    loc = amcl.AMCL(min_particles, max_particles, slow, fast,
                    amcl.MotionParameters(m.alpha1, m.alpha2, m.alpha3, m.alpha4, 0.0),
                    amcl.LaserParameters(s.z_hit, s.z_short, s.z_max, s.z_rand, s.sigma_hit, s.lambda_short, 0.05,
                                         max_beams), "differential")
    loc.set_map(amcl.create_occupancy_grid_from_list(np.asarray(occ.grid).tolist(), occ.resolution, occ.origin_x,
                                                     occ.origin_y))
    loc.set_laser_pose(amcl.Vector3D(0.0, 0.0, 0.0))
    return loc
