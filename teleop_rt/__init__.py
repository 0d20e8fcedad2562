"""teleop_rt: a fixed-step 1 kHz haptic bilateral teleoperation stack.

Implements the velocity-torque architecture of Kuschel & Buss (impedance-based transparency
analysis of haptic telepresence): two computed-torque-linearised robots (HSI and TO), a torque
P(ID) controller on the HSI, a velocity P(ID) controller on the TO, and a wave-variable
(scattering) channel with whole-tick delay lines.
"""

__version__ = "0.1.0"
