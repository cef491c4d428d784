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


def shown(text: object, limit: int = 200) -> str:
  """`text` from outside (a file, a peer process, a key in a checkpoint) as
  a message may quote it: every character a terminal or a renderer would act
  on instead of showing it (control characters such as ESC, newlines, DEL,
  the C1 range, bidi overrides and other format characters) becomes a
  visible escape (`\\x1b`, `\\n`, `\\u202e`), bytes that are not UTF-8 become
  `\\xNN`, and a text longer than `limit` is cut with '...'.

  A quoted name can then neither clear the screen, retitle the window, nor
  forge a second `error:` line.
  """
  if isinstance(text, (bytes, bytearray)):
    text = bytes(text).decode('utf-8', 'backslashreplace')
  text = str(text)
  cut = len(text) > limit
  out = []
  for char in text[:limit]:
    if char.isprintable():
      out.append(char)
    elif char == '\n':
      out.append('\\n')
    elif char == '\t':
      out.append('\\t')
    elif char == '\r':
      out.append('\\r')
    elif ord(char) < 0x100:
      out.append(f'\\x{ord(char):02x}')
    elif ord(char) < 0x10000:
      out.append(f'\\u{ord(char):04x}')
    else:
      out.append(f'\\U{ord(char):08x}')
  return ''.join(out) + ('...' if cut else '')


def one_line(message: object, limit: int = 20000) -> str:
  """A message as the single line main prints: its own lines joined, and
  anything a terminal would act on escaped (`shown`), so that no text
  quoted in it reaches the terminal raw."""
  joined = ' '.join(line.strip() for line in str(message).splitlines()
                    if line.strip())
  return shown(joined, limit)


def brief(error: BaseException, limit: int = 300) -> str:
  """``Type: first line`` of an exception in about `limit` characters. A
  longer line keeps its start and its end, where libraries put the reason
  (tensorstore: ``... Failed to write 47768 bytes to file 8: No space left
  on device [os_error_code='28']`` after two long paths)."""
  text = str(error).strip()
  first = text.splitlines()[0] if text else ''
  if len(first) > limit:
    tail = limit // 3
    first = f'{first[:limit - tail]} ... {first[-tail:]}'
  return f'{type(error).__name__}: {first}'


def printable(message: object, limit: int = 20000) -> str:
  """A message of several lines as a command prints it: each line through
  `shown` (so a newline quoted inside a name was already escaped where it
  was quoted, and nothing else a terminal acts on gets through)."""
  return '\n'.join(shown(line, limit) for line in str(message).split('\n'))
