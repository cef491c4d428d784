"""A JSON file whose top level is one long array, read element by element.

`json.loads` of a whole file builds every element before the caller can
look at any: a CLEVRER question file of `[{},{},...]` cost about 51 bytes
of memory per byte of file (48 MiB -> 2.38 GiB), so a file at a 1 GiB limit
needed ~51 GiB. Here each element is parsed on its own (within a window of
at most `max_element_chars`, grown as needed), handed to the caller, who
checks it and keeps only what it needs, before the next one is parsed: a
malformed element is refused as it is met, and the memory held is the
file's text, one element being parsed (at most `max_element_chars` of
text), and what the caller keeps.
"""

from __future__ import annotations

import json
import re
from typing import Any, Iterator

from slotformer_jax.files import depth_of
from slotformer_jax.files import UntrustedFileError

_SPACE = re.compile(r'[ \t\n\r]*')
_FIRST_WINDOW = 1 << 10
_DECODER = json.JSONDecoder()


def elements(text: str, *, where: str, max_element_chars: int,
             max_depth: int, items: str = 'elements') -> Iterator[Any]:
  """Each element of the JSON array `text`, in order, parsed only when the
  previous one has been taken.

  Raises:
    UntrustedFileError: `where` (the file) and the problem: not an array,
      invalid JSON (line and column), an element longer than
      `max_element_chars` characters or nested deeper than `max_depth`.
  """
  position = _SPACE.match(text).end()
  if not text.startswith('[', position):
    top = {'{': 'a dict', '"': 'a str', 't': 'a bool', 'f': 'a bool',
           'n': 'null'}.get(text[position:position + 1], 'no JSON list')
    raise UntrustedFileError(f'{where} is {top}, not a list of {items}')
  position = _SPACE.match(text, position + 1).end()
  if text.startswith(']', position):
    _end(text, position + 1, where)
    return
  index, window = 0, _FIRST_WINDOW
  while True:
    start = position
    value, position = _element(text, position, where, index,
                               max_element_chars, window)
    # The next element's first window: about twice this one (elements of a
    # file are alike), so the copies cost a few times the text, not more.
    window = min(max(_FIRST_WINDOW, 2 * (position - start)),
                 max_element_chars)
    if depth_of(value) > max_depth:
      raise UntrustedFileError(f'{where}: element {index} nests lists and '
                               f'objects deeper than {max_depth} levels')
    yield value
    del value
    position = _SPACE.match(text, position).end()
    if text.startswith(']', position):
      _end(text, position + 1, where)
      return
    if not text.startswith(',', position):
      raise _invalid(text, position, where, "Expecting ',' delimiter")
    position = _SPACE.match(text, position + 1).end()
    index += 1


def _element(text: str, position: int, where: str, index: int,
             max_chars: int, window: int) -> tuple[Any, int]:
  """The element that starts at `position` and where it ends, parsed in a
  copy of `window` characters of the text that doubles until the element
  fits (so one element's parse never builds more than `max_chars` of it)."""
  while True:
    piece = text[position:position + window]
    try:
      value, end = _DECODER.raw_decode(piece)
      if end < len(piece) or position + end >= len(text):
        return value, position + end
      # A number cut by the window's end parses as a shorter one: wider.
      error = json.JSONDecodeError('Element cut at the window', piece, end)
      if window >= max_chars:
        raise _invalid(text, position + end, where,
                       f'element {index} is longer than {max_chars} '
                       'characters')
      window = min(window * 2, max_chars)
      continue
    except RecursionError:
      raise UntrustedFileError(f'{where}: element {index} is nested too '
                               'deeply') from None
    except json.JSONDecodeError as error:
      if position + len(piece) >= len(text):
        raise _invalid(text, position + error.pos, where, error.msg) from None
      if window >= max_chars:
        raise _invalid(text, position + error.pos, where,
                       f'{error.msg}; element {index} is not valid within '
                       f'its first {max_chars} characters') from None
      window = min(window * 2, max_chars)
    except ValueError as error:  # an int of more digits than Python reads
      raise UntrustedFileError(f'{where}: element {index} cannot be read: '
                               f'{str(error)[:120]}') from None


def _end(text: str, position: int, where: str) -> None:
  if _SPACE.match(text, position).end() != len(text):
    raise _invalid(text, position, where, 'Extra data')


def _invalid(text: str, position: int, where: str,
             message: str) -> UntrustedFileError:
  line = text.count('\n', 0, position) + 1
  column = position - text.rfind('\n', 0, position)
  return UntrustedFileError(f'{where} is not valid JSON (line {line}, column '
                            f'{column}: {message})')
