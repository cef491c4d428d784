"""The error a user can fix: main prints its message as one line on stderr
and exits non-zero, without a traceback (unexpected errors keep theirs)."""


class UserError(Exception):
  """Missing data or checkpoint, a bad config, a workdir in use, ...: the
  message says what is wrong and what to run or change."""
