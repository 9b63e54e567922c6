"""The `gsc` command-line tool (installed as package `gscompress_cli`)."""
