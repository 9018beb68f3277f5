"""EMSGC's energy: the data term, the spatio-temporal event graph of the Potts term, and the label cost."""
