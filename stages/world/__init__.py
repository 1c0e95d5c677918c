"""World assembly stage: composes world.usda from the upstream layers."""
from .stage import STAGE

__all__ = ["STAGE"]
