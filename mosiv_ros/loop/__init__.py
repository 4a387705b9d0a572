"""Loop closure (stage 5): find the residual, trace it to a missing effect, add it, refit.

- ``residual``: per-object, per-frame residuals of a twin against the reconstruction, their
  time structure and their correlation with the state;
- ``library``: the candidate effects, each with its knobs and its residual signature;
- ``observations``: what the loop fits and scores, remade from the recording for a sensor
  effect (a camera time offset);
- ``closure``: the loop (``LoopClosure``) and its acceptance criterion;
- ``report``: ``close_loop`` (``mosiv close-loop``) and its Markdown, JSON and plots.

ROS-free, like the rest of the core.
"""
