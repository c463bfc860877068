"""Training the STM: the one training loop (loop) for a single model or a pack of seeds, the
auto-conditioning schedule and unroll it follows (autoconditioning), its batches of whole
demonstrations or windows of them (batches, windows), the validation metric (validation),
checkpoints to resume from (checkpoint), a model's weights alone as a study export carries them (weights),
subnormal floats flushed to zero (subnormals), Ctrl-C held until a step is whole (interrupts) and, on CUDA, an
iteration captured once as a CUDA graph and replayed (cuda_graph).
"""
