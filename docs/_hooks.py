"""mkdocs hooks: pages the site builds from the project's own sources, so they cannot
drift from them: the command-line reference (from the argument parser), the studies
(`optimise/README.md`) and the notebooks (`notebooks/*.ipynb`, with their outputs)."""

from __future__ import annotations

import argparse
from pathlib import Path

from mkdocs.plugins import event_priority
from mkdocs.structure.files import File, Files

ROOT = Path(__file__).resolve().parents[1]


def _cli_reference() -> str:
    from recoil_jax.apps._cli import build_parser

    parser = build_parser()
    parser.formatter_class = argparse.RawDescriptionHelpFormatter
    lines = [
        "# Command line",
        "",
        "Every command of `recoil-jax`, with its options, as `--help` prints them.",
        "",
        "```text",
        parser.format_help().rstrip(),
        "```",
    ]
    subparsers = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    for name, sub in subparsers.choices.items():
        sub.formatter_class = argparse.RawDescriptionHelpFormatter
        lines += ["", f"## `recoil-jax {name}`", "", "```text", sub.format_help().rstrip(), "```"]
    return "\n".join(lines) + "\n"


def _studies() -> str:
    text = (ROOT / "optimise" / "README.md").read_text()
    # The figures it shows live in docs/, beside this page.
    return text.replace("](../docs/", "](")


@event_priority(100)  # before mkdocs-jupyter looks for notebooks among the files
def on_files(files: Files, config) -> Files:
    files.append(File.generated(config, "cli.md", content=_cli_reference()))
    files.append(File.generated(config, "studies.md", content=_studies()))
    for notebook in sorted((ROOT / "notebooks").glob("*.ipynb")):
        # A plain file whose source folder is the repository: notebooks/<name>.ipynb.
        files.append(
            File(
                f"notebooks/{notebook.name}",
                src_dir=str(ROOT),
                dest_dir=config["site_dir"],
                use_directory_urls=config["use_directory_urls"],
            )
        )
    return files
