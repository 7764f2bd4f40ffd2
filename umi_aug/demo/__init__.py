"""The ``umi-aug demo`` command: every available stage end to end on the built-in default scene."""
