"""Multi-view capture datasets (Format v1, docs/dataset.md): writing, validating, loading and
importing from other tools' layouts. Used by the synthetic studio and by training."""

from .format import CameraSpec
from .loader import Dataset, Split, View, ViewKey, load_dataset
from .problems import DatasetError, Problem, Where
from .validate import validate_dataset
from .writer import DatasetWriter

__all__ = ["CameraSpec", "Dataset", "DatasetError", "DatasetWriter", "Problem", "Split", "View",
           "ViewKey", "Where", "load_dataset", "validate_dataset"]
