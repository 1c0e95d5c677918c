from .stage import STAGE

__all__ = ["STAGE"]
