; delta: a move beyond the build radius stops the print on line 5
G90
G1 Z2 F3000
G1 X5 Y0 F6000
G1 X8.5 Y0 F6000
G1 X0 Y0 F6000
