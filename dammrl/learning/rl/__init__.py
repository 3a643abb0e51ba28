"""DAMMRL: the dual-agent DQN that learns the human-robot model matching M_ij."""
