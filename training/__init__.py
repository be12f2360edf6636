"""Hydra jobs on top of torchconn: ``train_frames`` (the main job), ``convergence`` (the report's
experiments, computed by ``experiments`` and ``report_quantities``) and ``demo``.

In a checkout they run as ``python -m training.<job>``; the wheel installs this folder as
``torchconn.training`` with console scripts (``torchconn-frames``, ``torchconn-convergence``,
``torchconn-demo``), so imports between the jobs are relative.
"""
