"""Hydra config files of the CLIs (``train.yaml`` and its groups, ``render.yaml``, ``bench.yaml``, ...).

Importing this package (Hydra does, to find the files) registers the ``mvtn.pid`` resolver: run
dirs are ``<time>-<pid>``, so two runs started in the same second never share a folder.
"""
import os

from omegaconf import OmegaConf

OmegaConf.register_new_resolver("mvtn.pid", os.getpid, replace=True)
