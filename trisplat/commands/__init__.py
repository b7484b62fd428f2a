"""CLI subcommands: one module per `trisplat` command, each exposing main(argv) -> int."""
