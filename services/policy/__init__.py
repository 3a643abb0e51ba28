"""Policy service: the multi-model choice M_ij (a fixed model until DAMMRL lands)."""
