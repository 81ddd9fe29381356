# Gripper: routines for the vacuum gripper on Arm1's flange.
# Programs load this module and call Gripper.pick / Gripper.place.
module Gripper version 1.2

routine approach        # slow final approach down onto the part
  speed 20
  move 0 10 -20 0 55 0
end

routine pick
  call Gripper.approach
  wait 0.3              # vacuum builds up
  speed 60
  move 0 -10 -10 0 60 0 # lift clear
end

routine place
  speed 20
  move 90 10 -20 0 55 90
  wait 0.2              # vacuum released
  speed 60
  move 90 -10 -10 0 60 90
end
