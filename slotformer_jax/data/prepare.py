"""`python -m slotformer_jax.data.prepare ...`: the documented command; the
conversion itself lives in `data/convert/prepare.py`."""

import sys

from slotformer_jax.data.convert.prepare import main

if __name__ == '__main__':
  sys.exit(main())
