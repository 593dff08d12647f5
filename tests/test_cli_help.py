"""``glider-hil VERB --help`` shows the verb's description as it is written (example command
lines and bullets keep their lines), and the example commands it shows are commands the
verb takes."""

from __future__ import annotations

import importlib
import re

import pytest

from hil_service.cli import VERBS, build_parser, main

#: A bracketed optional part of an example (``[--resume]``), dropped before it is parsed.
OPTIONAL = re.compile(r"\[[^\[\]]*\]")


def _help(capsys: pytest.CaptureFixture[str], verb: str) -> str:
    with pytest.raises(SystemExit) as exit_info:
        main([verb, "--help"])
    assert exit_info.value.code == 0
    return capsys.readouterr().out


def _examples(doc: str, verb: str) -> list[str]:
    """The example commands of ``doc`` (indented lines starting ``glider-hil VERB``, with
    their backslash continuations joined), without their bracketed optional parts."""
    examples: list[str] = []
    lines = iter(doc.splitlines())
    for line in lines:
        if not line.strip().startswith(f"glider-hil {verb} "):
            continue
        command = line.strip()
        while command.endswith("\\"):
            command = command[:-1] + " " + next(lines).strip()
        examples.append(OPTIONAL.sub(" ", command))
    return examples


@pytest.mark.parametrize("verb", sorted(VERBS))
def test_a_verb_s_help_keeps_its_description_s_lines(capsys, verb: str) -> None:
    doc = importlib.import_module(VERBS[verb][0]).__doc__ or ""
    shown = set(_help(capsys, verb).splitlines())
    for line in doc.strip().splitlines():
        if line.strip():
            assert line.rstrip() in shown, f"{verb} --help reflowed: {line!r}"


def test_the_examples_in_the_help_are_commands_the_verbs_take() -> None:
    parsed = 0
    for verb, (module_name, _) in VERBS.items():
        doc = importlib.import_module(module_name).__doc__ or ""
        for example in _examples(doc, verb):
            if "..." in example:
                continue  # an elided command, not one to run
            build_parser(verb).parse_args(example.split()[1:])
            parsed += 1
    assert parsed >= 4  # serve's two, campaign's run and compare
