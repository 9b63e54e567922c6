"""`python -m gscompress_cli` runs `gsc`."""

from .main import cli

if __name__ == "__main__":
    cli(prog_name="gsc")
