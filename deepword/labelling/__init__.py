"""Labels in from annotation tools, predictions out to them (docs/labelling.md).

    deepword import --from {label-studio,cvat,coco} FILE --images DIR --out DATASET
    deepword export-labels --to {label-studio,cvat} --pred PRED.jsonl --out FILE

Modules, one idea each: ``label_studio``, ``cvat``, ``coco`` (each tool's format, read and, where it makes
sense, written), ``build`` (tool-independent assembly and checks of records), ``problems`` (every problem as one
line), ``importer`` (the dataset written all or nothing; ``deepword import``), ``export`` (``deepword
export-labels``). Torch-free, like the rest of the inference side.
"""

from deepword.labelling.build import CLASS_LABELS, COUPLE, LINK_LABELS, Summary
from deepword.labelling.coco import read_coco
from deepword.labelling.cvat import read_cvat, to_cvat
from deepword.labelling.export import export_labels, read_predictions
from deepword.labelling.importer import READERS, ImportResult, convert, import_labels, write_dataset
from deepword.labelling.label_studio import config as label_studio_config
from deepword.labelling.label_studio import read_label_studio, to_label_studio
from deepword.labelling.problems import LabellingError, Problems

__all__ = [
    "CLASS_LABELS", "COUPLE", "LINK_LABELS", "READERS",
    "ImportResult", "LabellingError", "Problems", "Summary",
    "convert", "export_labels", "import_labels", "label_studio_config", "read_coco", "read_cvat",
    "read_label_studio", "read_predictions", "to_cvat", "to_label_studio", "write_dataset",
]
