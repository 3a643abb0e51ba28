"""The comparison study of the paper: ``dammrl study``."""
