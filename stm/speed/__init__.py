"""How fast the STM trains and rolls out: `python -m stm.speed.bench` (bench, on the inputs of bench_inputs)
and the matrix-product floor an iteration is compared with (floor).
"""
