"""The project file: the Project (every input, parameter and pick, as TOML), its key declarations, the one
validation layer that the CLI, TUI and viewer call, the commented template and the text-file readers."""
