"""Test-wide settings.

The filter's tensors are small (26 x 26): one intra-op thread is fastest, and it keeps
the suite's run time stable on a busy 2-core machine (oversubscribed threads made
small matrix products two orders of magnitude slower here).
"""
import torch

torch.set_num_threads(1)
