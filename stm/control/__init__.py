"""From an STM plan to torques, the paper's post-processing: trajectory smoothing (smoothing), a
torque-controlled Sawyer in pybullet (torque_sim), the inverse dynamics model (idm), its training
data (idm_data) and study (idm_study), and stand-in plans when no trained STM is at hand (plans).
"""
