"""Errors a user can fix: main prints the message as one line on stderr and
exits non-zero, without a traceback (unexpected errors keep theirs).

The subclasses are also the built-in error a caller may already catch
(`except FileNotFoundError` keeps working for missing inputs).
"""


class UserError(Exception):
  """Missing data or checkpoint, a bad config, a workdir in use, ...: the
  message says what is wrong and what to run or change."""


class MissingInputError(UserError, FileNotFoundError):
  """A dataset, checkpoint or extraction that must exist first."""


class ConfigError(UserError, ValueError):
  """A config value that cannot work."""


class CommandLineError(UserError):
  """A flag value that names nothing (e.g. a --mode the config's stage
  table does not have): exit status 2, as absl's own flag errors."""
