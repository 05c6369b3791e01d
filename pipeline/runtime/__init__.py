"""The on-robot runtime: adaptive Monte Carlo localization on the laser map and its models.

numpy, scipy and numba only (never torch or OpenCV; a test checks). `grid` (map, distance field),
`motion` (odometry model), `sensor` + `kernels` (likelihood field, beam model), `sampling` (KLD,
systematic resampling), `estimate` (cluster mean), `amcl` (the filter and its states).
"""
