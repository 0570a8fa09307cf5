"""The commands (mvtn-train, mvtn-eval, ...): compose and check the config, call one function, map errors to exit codes."""
