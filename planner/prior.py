"""The embedded indoor prior (moved to :mod:`protocol.prior`, where the mapper's room labels read it too)."""

from protocol.prior import (
    ABSENT_P,
    DEFAULT_PRIOR_PATH,
    DEFAULT_SIZE_M,
    FORMAT,
    CatalogItem,
    IndoorPrior,
    PriorEntry,
    load_prior,
)

__all__ = ["ABSENT_P", "DEFAULT_PRIOR_PATH", "DEFAULT_SIZE_M", "FORMAT", "CatalogItem", "IndoorPrior", "PriorEntry",
           "load_prior"]
