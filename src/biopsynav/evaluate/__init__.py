"""The paper's evaluation (section 3): Table 1 (network) and Table 2 (TRE per lesion and
probe displacement for the network, the FE model and a rigid model), by simulation against a
finer FE model or from user-measured lesion positions. See ``docs/evaluation.md``."""

from .measured import evaluate_measured, read_measured
from .placement import Placement, place_probe, push_depths
from .run import evaluate_case, table2_markdown, table2_text, write_table2
from .simulation import run_simulation
from .table import BIN_EDGES_MM, BIN_NAMES, Record, Table, aggregate, bin_index, bin_name

__all__ = ["BIN_EDGES_MM", "BIN_NAMES", "Placement", "Record", "Table", "aggregate",
           "bin_index", "bin_name", "evaluate_case", "evaluate_measured", "place_probe",
           "push_depths", "read_measured", "run_simulation", "table2_markdown", "table2_text",
           "write_table2"]
