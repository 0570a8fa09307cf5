"""The config layer: one registry per option kind, the schemas, the shared value checks, and the checked composition of a command's config."""
