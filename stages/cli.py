"""The ``deepword`` command: one entry point for the pipeline and the tools around it.

    deepword run [hydra overrides...]     the pipeline (same as ``python -m pipeline``)
    deepword score --gt ROOT --pred FILE  score WORD-format predictions (deepword.scoring.score)
    deepword infer ...                    relations with the exported ONNX models (stages.inference.infer)
    deepword tune --dataset ROOT --out DIR  the detector's operating point chosen on your labelled images
    deepword show ROOT                    Fig. 5-style contact sheet of a dataset (stages.data.show)
    deepword import --from TOOL FILE --images DIR --out DATASET   labels from Label Studio, CVAT or COCO
                                          into a WORD-style dataset (deepword.labelling.importer)
    deepword export-labels --to TOOL --pred FILE --out FILE       predictions as pre-annotations for
                                          Label Studio or CVAT (deepword.labelling.export)

Each subcommand's module is imported only when it is chosen, so ``deepword infer`` never loads torch
and ``deepword run`` keeps the engine's fast no-op path.
"""

from __future__ import annotations

import importlib
import sys

COMMANDS = {
    "run": ("pipeline.cli", "run the pipeline with Hydra overrides"),
    "score": ("deepword.scoring.score", "score WORD-format predictions against a dataset"),
    "infer": ("stages.inference.infer", "relations of images or a dataset with the exported ONNX models"),
    "tune": ("stages.inference.tune", "choose the bundle's detector operating point on your labelled images"),
    "show": ("stages.data.show", "contact sheet of a WORD-style dataset"),
    "import": ("deepword.labelling.importer", "labels from Label Studio, CVAT or COCO into a WORD-style dataset"),
    "export-labels": ("deepword.labelling.export", "predictions as pre-annotations for Label Studio or CVAT"),
}


def usage() -> str:
    lines = ["usage: deepword COMMAND [ARGS...]", "", "commands:"]
    lines += [f"  {name:<13} {help_}" for name, (_, help_) in COMMANDS.items()]
    return "\n".join(lines + ["", "deepword COMMAND --help shows a command's options."])


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    if not argv or argv[0] in ("-h", "--help"):
        print(usage(), file=sys.stdout if argv else sys.stderr)
        return 0 if argv else 2
    command, rest = argv[0], argv[1:]
    if command not in COMMANDS:
        print(f"deepword: unknown command {command!r}\n\n{usage()}", file=sys.stderr)
        return 2
    module = importlib.import_module(COMMANDS[command][0])
    if command == "run":  # Hydra parses sys.argv itself
        sys.argv = [f"{sys.argv[0]} run", *rest]
        module.main()
        return 0
    code = module.main(rest)
    return int(code or 0)


if __name__ == "__main__":
    sys.exit(main())
