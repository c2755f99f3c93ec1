"""User-facing errors of the science side: one line, naming the file and field; exit code 2."""


class ModelInputError(ValueError):
    """Bad user input (robot name, URDF, conditions file, parameters). Printed as one line."""

    exit_code = 2
