"""``python -m stemmap`` runs the command-line interface."""

from stemmap.cli import main

main()
