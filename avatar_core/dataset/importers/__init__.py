"""Importers of other tools' capture layouts into Format v1 (docs/dataset.md)."""

from .easymocap import import_easymocap
from .vhap import import_vhap

__all__ = ["import_easymocap", "import_vhap"]
