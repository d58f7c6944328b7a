"""`python -m slamreloc.cli`: the `slamreloc` command."""

from slamreloc.cli import run

run()
