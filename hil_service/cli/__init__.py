"""``glider-hil``: one console script, one module per verb (rosbag2 style)."""

from __future__ import annotations

import argparse
import importlib
import sys
from collections.abc import Sequence

from hil_service.process_tuning import single_threaded_blas

#: verb → (module with add_arguments/run, one-line help)
VERBS: dict[str, tuple[str, str]] = {
    "emulate": ("plant_emulator.cli", "run the emulated glider autopilot over MAVLink"),
    "serve": ("hil_service.cli.serve", "run the HIL service: MAVLink in, Zenoh out, MCAP log"),
    "demo": ("hil_service.cli.demo", "emulator + service + Zenoh peer on loopback, summary"),
    "experiment": ("hil_service.cli.experiment", "identification and control experiments"),
    "replay": ("hil_service.cli.replay", "replay a log through the service path (--check)"),
    "info": ("hil_service.cli.info", "duration, channels and configuration of a log"),
    "report": ("hil_service.cli.report", "figures and a Markdown summary from a log"),
    "import": ("hil_service.cli.import_tlog", "a .tlog or a glider's field data into an MCAP log"),
    "router": ("hil_service.cli.router", "a Zenoh router for services on several processes"),
    "campaign": ("hil_service.cli.campaign", "many lockstep HIL missions, scored; compare two"),
    "fleet": ("hil_service.cli.fleet", "live table of every served vehicle on the Zenoh network"),
}


def build_parser(only: str | None = None) -> argparse.ArgumentParser:
    """Every verb with its arguments; with ``only``, that verb's alone (the others listed
    without theirs), so that one verb's run imports one verb's modules."""
    parser = argparse.ArgumentParser(prog="glider-hil", description=__doc__)
    # A verb's description is its module's docstring, laid out as written: example command
    # lines and bullets read as such, not reflowed into one paragraph.
    raw = argparse.RawDescriptionHelpFormatter
    verbs = parser.add_subparsers(dest="verb", required=True, metavar="VERB")
    for verb, (module_name, help_text) in VERBS.items():
        if only is not None and verb != only:
            verbs.add_parser(verb, help=help_text)
            continue
        module = importlib.import_module(module_name)
        sub = verbs.add_parser(
            verb, help=help_text, description=module.__doc__, formatter_class=raw
        )
        module.add_arguments(sub)
        sub.set_defaults(run=module.run)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    # Importing every verb's modules (matplotlib, python-control, scipy: 2 s of CPU) for each
    # command cost a `fleet` or `router` started next to a running fleet that much CPU.
    single_threaded_blas()  # before a verb's modules load numpy
    arguments = list(sys.argv[1:] if argv is None else argv)
    only = arguments[0] if arguments and arguments[0] in VERBS else None
    args = build_parser(only).parse_args(arguments)
    return int(args.run(args) or 0)
