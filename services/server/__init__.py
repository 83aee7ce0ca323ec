"""The cristal localization server: Render & Match (or P&L) per client behind Zenoh queryables."""
