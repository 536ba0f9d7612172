"""`python -m magcal_cli` runs the command line."""

from magcal_cli.cli.main import main

main()
