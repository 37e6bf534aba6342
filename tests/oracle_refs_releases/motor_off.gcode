; kestimator test: M84 / M18 (extras/stepper_enable.py): before set_motors_enable (v0.12.0,
; v0.13.0, Kalico v2026.07.00) motor_off dwells twice whether or not a motor was on, with no
; flush of step generation first; today's flushes first and dwells only when one was on
G90
M83
SET_PRESSURE_ADVANCE ADVANCE=0.04
G1 X20 Y20 F6000
;LAYER:1
G1 X60 Y20 E2 F3000
G1 X60 Y60 E2
M84
;LAYER:2
M84
M18
;LAYER:3
G28
G1 X30 Y30 Z0.3 F6000
G1 X70 Y30 E2 F3000
G1 X70 Y70 E2
M18 X Y
;LAYER:4
G28 X Y
G1 X10 Y10 F6000
G1 X50 Y10 E1
M84
G4 P50
;LAYER:5
G28
G1 X5 Y5 F6000
