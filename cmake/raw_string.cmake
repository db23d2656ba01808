# ag2gs_raw_string(TEXT OUT_VAR TAG): OUT_VAR = TEXT as C++ raw string
# literals delimited by TAG, in chunks of 12000 characters (some compilers
# limit the length of one literal; adjacent literals concatenate). "" for
# an empty TEXT.
function(ag2gs_raw_string text out tag)
  string(LENGTH "${text}" len)
  set(pieces "")
  set(pos 0)
  while(pos LESS len)
    string(SUBSTRING "${text}" ${pos} 12000 chunk)
    string(APPEND pieces "R\"${tag}(${chunk})${tag}\"\n")
    math(EXPR pos "${pos} + 12000")
  endwhile()
  if(pieces STREQUAL "")
    set(pieces "\"\"")
  endif()
  set(${out} "${pieces}" PARENT_SCOPE)
endfunction()
