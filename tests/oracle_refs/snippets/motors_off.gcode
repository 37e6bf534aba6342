; M84 unhomes every axis: the XY move after it stops the print on line 8
G90
M83
G1 X3 Y3 Z1 F6000
M84
G1 E1 F300
G4 P100
G1 X4 Y4 F6000
