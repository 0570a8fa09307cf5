"""mvtn-eval config (its own search path: task/robustness are plain keys here, not the training groups)."""
