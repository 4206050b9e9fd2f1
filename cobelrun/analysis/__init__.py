"""Post-run analysis: plain functions over arrays and DataFrames that return DataFrames."""
