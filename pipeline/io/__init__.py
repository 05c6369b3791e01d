"""Data contracts: Parquet tables with schema versions, ROS map_server maps, site captures, CARMEN logs."""
