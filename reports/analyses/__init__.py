"""Analyses across studies that RESULTS.md and its notebook pages quote, each a table and a figure: success vs
number of demonstrations (data_scaling), a lever's studies side by side (levers), where changing-goal, stacking and
pick-and-place episodes fail (goal_switch, stacking, pick_place_failures), pick-and-place success judged on the block
beside the strict criterion (placement), multimodal demonstrations (multimodal),
mode use per episode (mode_use) and success vs training iterations (success_vs_iterations).
"""
