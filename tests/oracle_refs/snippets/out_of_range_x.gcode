; a move beyond position_max of X stops the print on the second G1 line
G90
G1 X20 Y20 F6000
G1 X260 Y20 F6000
G1 X30 Y30 F6000
