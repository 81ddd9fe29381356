"""Where the official OPC Foundation information models (NodeSet2 files) come from."""

from uacell.models.model_file import ModelFile
from uacell.models.source import (
    ModelError,
    fetch_models,
    locate_models,
    models_dir,
    official_models,
)
from uacell.models.tables import FsmTable, StateInfo, StateTables, TableLoader, TransitionInfo, fsm_table

__all__ = [
    "FsmTable",
    "ModelError",
    "ModelFile",
    "StateInfo",
    "StateTables",
    "TableLoader",
    "TransitionInfo",
    "fetch_models",
    "fsm_table",
    "locate_models",
    "models_dir",
    "official_models",
]
