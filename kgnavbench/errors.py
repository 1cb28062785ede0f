"""The package's one error base class. Every error a user can cause (an unknown kitchen, method, plugin
or option, a corrupt checkpoint or table spec, a run in use) is a KgnavbenchError, each stage's own
class below it (EvalError, TableError, ...); the command line catches it once (`cli.main`) and prints
one `kgnavbench: error: ...` line with exit status 2, never a traceback. The stages' classes are also
ValueErrors (ClaimError a RuntimeError), as before there was a base. A helper without a stage number.
"""


class KgnavbenchError(Exception):
    """Bad input or a refused step: its message is one line that names the problem."""
