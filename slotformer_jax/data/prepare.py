"""`python -m slotformer_jax.data.prepare ...`: the documented command; the
conversion itself lives in `data/convert/prepare.py`."""

import signal
import sys

try:
  from slotformer_jax.data.convert.prepare import main
except KeyboardInterrupt:  # Ctrl-C while the libraries import
  if __name__ == '__main__':  # not a worker re-importing this file
    print('interrupted: Ctrl-C; nothing was converted yet', file=sys.stderr)
  sys.exit(128 + signal.SIGINT)

if __name__ == '__main__':
  sys.exit(main())
