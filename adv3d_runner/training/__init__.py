"""Data generation and training of the learned autonomy models (``adv3d train ...``).

Apart from the runtime stack on purpose: :mod:`adv3d_runner.autonomy` runs the models and never
imports this package; the modules here simulate scenes to make training data (so they sit above
``sim`` in the layer order) and train and evaluate the models.

* :mod:`.detector_data`   simulated LiDAR frames + ground-truth boxes for the BEV detector
* :mod:`.detector_train`  detector loss, training loop, AP evaluation
* :mod:`.predictor_data`  tracked noisy detections -> predictor features + true futures
* :mod:`.predictor_train` predictor training loop, held-out evaluation against the baselines
* :mod:`.cli`             the ``adv3d train detector|predictor`` commands
"""
