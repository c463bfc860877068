"""The state transition model (STM) of the paper and everything that trains and uses it.

Top level, the model itself: its configuration (config), the variants of the ablation (variants),
the LSTM with its deterministic or mixture density head (model, mdn), the fed-back tip position
(fk), the hand-written LSTM step the auto-conditioned unroll uses (lstm_step), its self-fed steps in C++
(self_fed), the MDN loss as one C++ op (mdn_fused), the C++ extension's build and which step kernel runs
(cpp_ext), K seeds' models as one batched model (packed, packed_lstm_step), closed-loop rollouts of one model
or of K at once (rollout) and where they run (device: --device auto|cpu|cuda[:N]).
Subpackages: training (the training loop), control (smoothing and inverse dynamics for torque
control of STM plans), speed (the training-speed bench).
"""
