"""``python -m pipeline.lab.synth``: the synth subcommand on its own."""

import sys

from pipeline.cli import main

sys.exit(main(["synth", *sys.argv[1:]]))
