"""geocues package."""
