this is not a LAS file at all, just text with a .las name
