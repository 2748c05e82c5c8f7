"""Looking inside trained runs: credit per agent (`relevance`) and RDN's credit diagnostics."""
