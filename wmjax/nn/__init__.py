"""Flax Linen modules: the ST-DiT world model and its layers."""

from wmjax.nn.dit import COND_MODES, STDiT
from wmjax.nn.flops import forward_flops

__all__ = ["COND_MODES", "STDiT", "forward_flops"]
