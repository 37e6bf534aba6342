; G28 leaves each axis at its position_endstop (delta: at its home position)
G90
M83
G1 X5 Y5 Z1 F6000
G28
;LAYER_CHANGE
G1 X10 Y10 Z2 F12000
G1 X0 Y4 F12000
G1 E1 F1200
G28 X
;LAYER_CHANGE
G1 X3 Y3 Z3 F9000
G1 X1 Y-1 F9000
