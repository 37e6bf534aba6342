; polar: a move beyond stepper_arm's position_max stops the print on line 5
G28
G90
G1 X100 Y0 F6000
G1 X200 Y200 F6000
G1 X100 Y10 F6000
