"""Exceptions raised by vsrd-mi for bad input."""
class DataError(ValueError):
    """Bad or missing input data; the message names the file and the problem."""
    def __init__(self, path, problem):
        self.path, self.problem = str(path), problem
        super().__init__(f"{path}: {problem}")
