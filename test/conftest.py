"""Shared test settings: small thread counts so the suite behaves the same on 2-core CI machines."""

import os

import torch

os.environ.setdefault("NOCAL_TEST", "1")
torch.set_num_threads(min(2, os.cpu_count() or 1))
