"""The command line: ``fieldtool ...`` subcommands (``main``), their handlers and the console output."""
