"""How fast the STM trains and rolls out: `python -m stm.speed.bench` (bench, on the inputs of bench_inputs;
its printed lines: summary), the floor an iteration is compared with (floor: its products' FLOPs at the core's
peak GEMM rate) and the iteration on a trained checkpoint's weights (trained).
"""
