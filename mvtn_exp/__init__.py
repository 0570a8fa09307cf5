"""mvtn-exp."""
