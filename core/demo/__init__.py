"""The demo scenes (the thigh and the arm), the implicit solids they are made of and the
meshing of those solids into closed triangle surfaces."""
