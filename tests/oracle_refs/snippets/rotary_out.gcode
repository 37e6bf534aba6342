; rotary_delta: a move beyond the build radius stops the print on line 4
G90
G1 X20 Y20 Z5 F6000
G1 X220 Y20 F6000
G1 X0 Y0 F6000
