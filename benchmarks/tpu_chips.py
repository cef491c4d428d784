"""The TPU chips `benchmarks/tpu_compile.py` compiles for, by device kind.

Kept apart so that `benchmarks/tpu_compile_table.py` reads the peaks
without importing the pipeline.
"""

GiB = 2**30

# Public spec sheets (cloud.google.com/tpu/docs/v5e, /v4): HBM per chip,
# peak bf16 matmul FLOP/s per chip, HBM bandwidth per chip. No float32
# peak is published: XLA:TPU runs float32 matmuls at the default precision
# as bfloat16 passes, so the bf16 peak is the floor used for both dtypes.
CHIPS = {
    'TPU v5 lite': dict(name='v5e', hbm=16 * GiB, peak_flops=197e12,
                        hbm_bandwidth=819e9),
    'TPU v4': dict(name='v4', hbm=32 * GiB, peak_flops=275e12,
                   hbm_bandwidth=1228e9),
}
