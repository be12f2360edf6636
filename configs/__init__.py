"""Hydra configurations of the jobs in ``training/`` (installed as ``torchconn.configs``, read through ``pkg://``)."""
