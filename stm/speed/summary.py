"""The bench's result as the lines `python -m stm.speed.bench` prints without --json."""

from __future__ import annotations


def summary(result: dict) -> str:
    peak = result["peak_gflops"]
    lines = [f"torch {result['torch']}, {result['threads']} thread(s), load {result['load_average_before'][0]:.1f}, "
             f"peak GEMM ({peak['size']}^3) {peak['fp32']:.0f} GFLOP/s fp32, {peak['bf16']:.0f} bf16"]
    for r in result["training"]:
        ms = r["ms_per_iter"]
        lines.append(f"{r['size']:>10} (3x{r['hidden']}, {r['mixtures']} Gaussians, batch {r['batch']}, "
                     f"{r['steps']} steps, D={r['state_dim']}): "
                     + ", ".join(f"{k} {v:.1f} ms" for k, v in ms.items())
                     + f" | ac2/tf {r['ratio_ac_u2v2_over_tf']:.2f}, ac5/tf {r['ratio_ac_u5v5_over_tf']:.2f},"
                     f" tf/plain {r['ratio_tf_over_plain']:.2f} | packed x{r['packed_k']}: speedup tf "
                     f"{r['packed_speedup_tf']:.2f}, ac {r['packed_speedup_ac']:.2f} | windows of {r['window']} "
                     f"after {r['burn_in']}: x{r['window_speedup_packed_ac_u5v5']:.2f} per packed ac5 iteration")
        floor = r["floor_ms_per_model_iter"]
        lines.append(f"{'':>10} floor (GFLOP at the peak), ms per model-iteration fp32/bf16: "
                     + ", ".join(f"{s} {r['gflop_per_model_iter'][s]['total']:.2f} GFLOP "
                                 f"{floor['fp32'][s]:.1f}/{floor['bf16'][s]:.1f}" for s in floor["fp32"])
                     + " | floor_ratio " + ", ".join(f"{k} {v:.2f}" for k, v in r["floor_ratio"].items())
                     + " | bf16 floor_ratio " + ", ".join(f"{k} {v:.2f}" for k, v in r["bf16_floor_ratio"].items())
                     + " | over the products replayed " + ", ".join(f"{k} {v:.2f}"
                                                                   for k, v in r["products_ratio"].items())
                     + " | bf16/fp32 " + ", ".join(f"{k} {v:.2f}" for k, v in r["bf16_over_fp32"].items()))
    if "trained_weights" in result:
        tw = result["trained_weights"]
        lines.append(f"{tw['checkpoint']} ({tw['task']}, iteration {tw['iteration']}, {tw['head']} head, u={tw['u']} "
                     f"v={tw['v']}, {tw['step_kernel']}): pack of {tw['packed_k']} "
                     f"{tw['ms_per_iter']['flushed']:.1f} ms per iteration with subnormals flushed, "
                     f"{tw['ms_per_iter']['ieee']:.1f} ms kept: x{tw['subnormal_slowdown']:.2f}")
    if "fk" in result:
        fk = result["fk"]
        us, calls = fk["us_per_call"], fk["aten_calls"]
        lines.append("tip FK, us per call, closed form / pytorch-kinematics (ATen calls): " + ", ".join(
            f"{n} (batch {b}) {us[n]['closed_form']:.0f}/{us[n]['pytorch_kinematics']:.0f}"
            f" ({calls[n]['closed_form']}/{calls[n]['pytorch_kinematics']})" for n, b in fk["batch"].items()))
    if "rollouts" in result:
        ro = result["rollouts"]
        lines.append(f"rollouts: {ro['rollouts']} x {ro['steps']} steps with FK grounding in {ro['seconds']:.2f} s; "
                     f"{ro['packed_k']} models batched {ro['packed_seconds']:.2f} s, one after the other "
                     f"{ro['separate_seconds']:.2f} s")
    return "\n".join(lines)
