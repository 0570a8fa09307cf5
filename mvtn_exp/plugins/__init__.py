"""The code of mvtn-exp's Hydra plugins (the trade search's sweeper); hydra_plugins/ holds the thin classes Hydra finds."""
