"""The package's version (from its installed metadata): what a campaign's identity and
`recoil-jax --version` say. A module of its own so that no part of the package imports
it back from the top level."""

from __future__ import annotations

import importlib.metadata

__all__ = ["__version__"]

__version__ = importlib.metadata.version("recoil-jax")
