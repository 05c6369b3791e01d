"""The embedded reference site: a generated office floor with rendered 6-view captures, boxes, laser runs.

Modules: `scene` (floor plan and objects from a preset and a seed), `assets` (real furniture meshes and
photographic textures from Debian's Sweet Home 3D packages, procedural fallback), `render` (moderngl on
headless EGL: RGB + instance-id buffers), `laser` (map rasterisation and scan casting), `trajectories`
(mapping/query runs, odometry noise, kidnappings), `synth` (writes a capture directory).
"""
