; deltesian: a move beyond the slow-down X makes Klipper 84104bbbd fail on line 5
; (its check_move reads self.max_velocity, which it never sets)
G90
G1 X20 Y50 Z5 F6000
G1 X50 Y10 F9000
G1 X0 Y10 F9000
