"""Reader for the reference implementation's processed-scene format."""
