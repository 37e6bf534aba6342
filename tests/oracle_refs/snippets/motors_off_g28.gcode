; M84, then G28: moves are allowed again (from the homing positions)
G90
G1 X3 Y3 Z1 F6000
M84
G28
G1 X5 Y5 Z2 F6000
;LAYER_CHANGE
G1 X0 Y0 F6000
G1 X2 Y1 F6000
