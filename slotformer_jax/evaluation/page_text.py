"""Text from files (method, metric and split names of eval/metrics.json, a
run's identity) as the explorer page may show it: a text node shows a
bidi override (U+202E turns 'videos' into 'soediv'), an isolate, a zero-width
or another format character, and a control character such as ESC, as what
it does rather than as what it is. Each becomes a visible escape
(`errors.shown`: `\\u202e`, `\\x1b`); line breaks stay (the footer's
preformatted notes have several lines).
"""

from __future__ import annotations

from typing import Any

from slotformer_jax.errors import printable


def on_page(text: str) -> str:
  """`text` with every character a renderer acts on made visible."""
  if text.isprintable():  # the usual case, at C speed (images' data URIs)
    return text
  return printable(text, max(len(text), 1))


def page_safe(value: Any) -> Any:
  """`value` (the page's JSON: dicts, lists, texts, numbers) with every
  text and every key through `on_page`; the same name gives the same key
  everywhere, so the page's lookups by name still meet."""
  if isinstance(value, str):
    return on_page(value)
  if isinstance(value, dict):
    return {on_page(k) if isinstance(k, str) else k: page_safe(v)
            for k, v in value.items()}
  if isinstance(value, (list, tuple)):
    return [page_safe(v) for v in value]
  return value
