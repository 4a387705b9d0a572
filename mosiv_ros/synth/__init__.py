"""Synthetic recordings with known ground truth, ROS-free.

``shapes``: an analytic sample (spheres on closed-form paths). The physics-based recorder:
``scene_file`` (the YAML schema) -> ``layout`` (particles at t = 0, geometric checks) ->
``recorder`` (simulate with ``mosiv_ros.sim``, render with ``render``/``cameras``, write the bag
and the ``ground_truth`` sidecars), with ``effects`` (declared or undeclared) and ``bodies``
(shapes as particles); ``suite`` generates a benchmark of such scenes.
"""
