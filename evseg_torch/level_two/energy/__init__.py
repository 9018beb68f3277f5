"""EMSGC's energy: the data term (:mod:`.data_term`), the spatio-temporal event graph of the Potts term
(:mod:`.graph`) and the label cost (:mod:`.label_cost`)."""
