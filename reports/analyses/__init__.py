"""Analyses across studies that RESULTS.md quotes, each a table and a figure: success vs number
of demonstrations (data_scaling), a lever's studies side by side (levers), where changing-goal
and stacking episodes fail (goal_switch, stacking), multimodal demonstrations (multimodal) and
success vs training iterations (success_vs_iterations).
"""
