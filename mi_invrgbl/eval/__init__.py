"""The evaluation library: how a (fitted) scene is scored.

* :mod:`.metrics`      -- image, material and LiDAR metrics (PSNR, SSIM,
  RMSE/MAE, angular error, scale-fitted albedo RMSE, ray drop, range error).
* :mod:`.inputs`       -- the scene, frames and observations to score (EXR
  channels read by name).
* :mod:`.rendering`    -- rendering a frame's camera and LiDAR, swapping the sky.
* :mod:`.ground_truth` -- material and sun metrics against a synthetic street's truth.
* :mod:`.baselines`    -- the nearest-neighbour LiDAR intensity lookup.
* :mod:`.scoring`      -- :func:`.scoring.evaluate`: every selected frame
  scored, the table, ``metrics.json``.
* :mod:`.baselines`    -- the nearest-neighbour LiDAR intensity baseline.
* :mod:`.lidar_novel_view` -- LiDAR novel-view scoring on raw held-out points.

``mi-invrgbl eval`` (:mod:`mi_invrgbl.commands.eval`) only parses its
arguments and calls :func:`.scoring.evaluate`; the benchmarks under
``tests/bench/`` use the library directly.
"""
